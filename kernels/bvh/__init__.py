"""Bounding volume hierarchies: the task-pool builders (spatial median and binned SAH, 2012
paper, sec. 4), the node layout, the wide (4- or 8-child) tree collapsed from it, and
closest-hit / any-hit traversal of either."""

from .api import METHODS, Bvh, build_bvh, trace
from .binary_traversal import STACK_SIZE
from .node import BvhArrays, BvhNode
from .refit import REBUILD_RATIO, refit_bvh
from .stats import BvhStats
from .traversal import closest_hit, traverse

__all__ = [
    "METHODS", "REBUILD_RATIO", "STACK_SIZE", "Bvh", "BvhArrays", "BvhNode", "BvhStats",
    "build_bvh", "closest_hit", "refit_bvh", "trace", "traverse",
]
