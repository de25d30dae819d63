"""scenesort's engine: Warp kernels for the task pool, BVH construction and traversal,
divide-and-conquer ray tracing and ambient occlusion.

Packages (each imports only those before it): `core` (geometry, validation, launch helpers,
device arrays) <- `pool` (the task pool and its worker) <- `bvh`, `dacrt` <- `render`
(camera, sampling, AO). This module is the public API.
"""

from .bvh import Bvh, build_bvh, trace
from .core import Hits
from .dacrt import dacrt_trace
from .pool import PoolError
from .render import AoResult, Camera, ambient_occlusion, render_ao

__all__ = [
    "AoResult", "Bvh", "Camera", "Hits", "PoolError", "ambient_occlusion", "build_bvh",
    "dacrt_trace", "render_ao", "trace",
]
