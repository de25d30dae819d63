"""What a two-level scene's build made and what it cost (`Scene.stats`)."""

from __future__ import annotations

from dataclasses import dataclass

from ..core.record import Record


@dataclass(frozen=True, slots=True)
class SceneStats(Record):
    """`build_scene`'s statistics (docs/kernels-api.md); times in ms."""

    build_ms: float  # the top level's wall time (the meshes' BVHs are built before)
    compile_ms: float  # Warp's, not in build_ms
    phase_ms: dict[str, float]  # instances, prepare, SplitPlane, PPS, Swap, AABB, Nodes, top
    instances: int  # in the list
    instances_built: int  # in the top level: valid and visible
    meshes: int
    meshes_built: int  # meshes with a Bvh (not None)
    top_nodes: int
    top_depth: int
    nbytes: int  # device bytes (Scene.nbytes)
    device: str
