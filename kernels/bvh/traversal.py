"""Closest-hit and any-hit traversal of a built BVH: the binary tree (binary_traversal's
loop with the slab test and the watertight leaf test), or the wide tree (wide_traversal);
`traverse` picks by the tree.

The binary stack holds binary_traversal.STACK_SIZE entries, as many as the deepest tree
`build_bvh` makes, so it cannot overflow.
"""

from __future__ import annotations

import warp as wp

from ..core.claim import Claims, claimed_items
from ..core.compile_options import MODULE_OPTIONS
from ..core.ray import (
    Hit,
    Ray,
    flag_invalid_rays,
    hit_distance,
    intersect_box,
    make_ray,
    no_hit,
    per_ray,
)
from .binary_traversal import BinaryTree, make_binary_traversal
from .leaf import finish_traversal, intersect_leaf, leaf_order_hit, wide_leaves
from .node import BvhArrays
from .wide_traversal import traverse_wide

# 64-thread blocks on CUDA: Conference's 1024^2 camera rays ran at 1.20 GRays/s on an H200
# against 1.07 with 256 (32: 1.21, 128: 1.19, 512: 0.87); a CPU launch ignores it
wp.set_module_options({**MODULE_OPTIONS, "block_dim": 64})

# the binary tree's traversal, from its box test and its leaf
traverse_binary_tree = make_binary_traversal(BinaryTree(
    tree=BvhArrays, query=Ray, result=Hit, miss=no_hit, enter=intersect_box,
    leaf=intersect_leaf, distance=hit_distance, finish=leaf_order_hit, module=__name__,
    name="traverse_binary_tree"))


@wp.func
def traverse_binary(bvh: BvhArrays, r: Ray, tmin: float, tmax: float, any_hit: bool) -> Hit:
    """`traverse_leaf_order` on the binary tree (bvh.nodes)."""
    return traverse_binary_tree(bvh, bvh.nodes, r, tmin, tmax, any_hit)


@wp.func
def traverse_leaf_order(bvh: BvhArrays, r: Ray, tmin: float, tmax: float,
                        any_hit: bool) -> Hit:
    """`traverse`'s hit as the traversal found it: hit.triangle its reference (leaf.py), t,
    u, v unrefined (`leaf.finish_traversal` finishes it). Two-level scenes compare these
    across instances and finish the closest alone."""
    if wide_leaves(bvh):
        return traverse_wide(bvh, r, tmin, tmax, any_hit)
    return traverse_binary(bvh, r, tmin, tmax, any_hit)


@wp.func
def traverse(bvh: BvhArrays, r: Ray, tmin: float, tmax: float, any_hit: bool) -> Hit:
    """Closest hit in [tmin, tmax], or with `any_hit` the first hit found (no float64
    refinement, no ordering bookkeeping beyond the stack), through the wide tree where the
    BVH has one (bvh.width 4 or 8) on CPU, else the binary tree: the same hits either way
    (the triangle may differ only between hits at equal t). Pass `any_hit` as a run-time
    value (a kernel argument): with a literal True, the CPU build of a kernel ran 25-30%
    slower in our measurements (clang specialises the loop badly)."""
    return finish_traversal(bvh, r, tmin, tmax, traverse_leaf_order(bvh, r, tmin, tmax, any_hit),
                            any_hit)


@wp.func
def closest_hit(bvh: BvhArrays, origin: wp.vec3, direction: wp.vec3, tmin: float,
                tmax: float) -> Hit:
    """The nearest hit with t in [tmin, tmax]."""
    return traverse(bvh, make_ray(origin, direction), tmin, tmax, False)


@wp.kernel
def trace_kernel(
    bvh: BvhArrays,
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    tmin: wp.array(dtype=float),  # per ray, or one value for all
    tmax: wp.array(dtype=float),
    find_any: int,
    out_t: wp.array(dtype=float),
    out_triangle: wp.array(dtype=int),
    out_u: wp.array(dtype=float),
    out_v: wp.array(dtype=float),
    invalid: wp.array(dtype=int),  # set to 1 where a ray is one as_rays refuses
    claims: Claims,
):
    items = claimed_items(claims, wp.tid())
    flag_invalid_rays(origins, directions, items[0], items[1], invalid)
    for i in range(items[0], items[1]):
        r = make_ray(origins[i], directions[i])
        h = traverse(bvh, r, per_ray(tmin, i), per_ray(tmax, i), find_any != 0)
        out_t[i] = h.t
        out_triangle[i] = h.triangle
        out_u[i] = h.u
        out_v[i] = h.v
