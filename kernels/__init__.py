"""scenesort's engine: Warp kernels for the task pool, BVH construction and traversal."""

from .ao import AoResult, ambient_occlusion, render_ao
from .api import Bvh, Hits, build_bvh, trace
from .camera import Camera
from .dacrt_api import dacrt_trace
from .pool import PoolError

__all__ = [
    "AoResult", "Bvh", "Camera", "Hits", "PoolError", "ambient_occlusion", "build_bvh",
    "dacrt_trace", "render_ao", "trace",
]
