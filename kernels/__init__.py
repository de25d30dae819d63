"""scenesort's engine: Warp kernels for the task pool, BVH construction and traversal,
divide-and-conquer ray tracing and ambient occlusion.

Packages (each imports only those before it): `core` (geometry, validation, launch helpers,
device arrays) <- `pool` (the task pool and its worker) <- `bvh`, `dacrt` <- `scene` (two
levels: per-mesh BVHs under instance transforms) <- `render` (camera, sampling, AO,
culling). This module is the public API.
"""

from .bvh import REBUILD_RATIO, Bvh, build_bvh, refit_bvh
from .core import Hits
from .dacrt import DacrtStats, dacrt_trace
from .pool import PoolError
from .render import (
    AoOptions,
    AoResult,
    Camera,
    ambient_occlusion,
    mesh_box,
    render_ao,
    render_film,
    surface_ao,
    visible_instances,
    visible_triangles,
)
from .scene import Scene, build_scene, place_instances, trace

__all__ = [
    "REBUILD_RATIO", "AoOptions", "AoResult", "Bvh", "Camera", "DacrtStats", "Hits",
    "PoolError", "Scene", "ambient_occlusion", "build_bvh", "build_scene", "dacrt_trace",
    "mesh_box", "place_instances", "refit_bvh", "render_ao", "render_film", "surface_ao", "trace",
    "visible_instances", "visible_triangles",
]
