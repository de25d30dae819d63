"""scenesort's engine: Warp kernels for the task pool, BVH construction and traversal."""

from .api import Bvh, Hits, build_bvh, trace
from .pool import PoolError

__all__ = ["Bvh", "Hits", "PoolError", "build_bvh", "trace"]
