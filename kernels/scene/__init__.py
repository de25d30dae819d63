"""Two-level scenes: per-mesh BVHs (object space) under instance transforms, with a top
level built on the task pool over the instances, and tracing through both levels."""

from .api import Placement, Scene, build_scene, bvh_nbytes, place_instances, trace
from .stats import SceneStats
from .top import InstanceHit, SceneArrays, traverse_scene

__all__ = [
    "InstanceHit", "Placement", "Scene", "SceneArrays", "SceneStats", "build_scene",
    "bvh_nbytes", "place_instances", "trace", "traverse_scene",
]
