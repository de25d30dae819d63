"""Closest-hit and any-hit traversal of a built BVH (near child first, explicit stack):
the binary tree here, the wide tree in wide_traversal; `traverse` picks by the tree.

The binary stack holds STACK_SIZE entries, as many as the deepest tree `build_bvh` makes
(`max_depth` <= STACK_SIZE), so it cannot overflow. Popped nodes whose entry distance is
beyond the closest hit found so far are skipped.
"""

from __future__ import annotations

import warp as wp

from ..core.box import INF
from ..core.compile_options import MODULE_OPTIONS
from ..core.ray import Hit, Ray, intersect_box, make_ray, per_ray
from .leaf import finish_hit, intersect_leaf
from .node import BvhArrays
from .wide_traversal import traverse_wide

# 64-thread blocks on CUDA: Conference's 1024^2 camera rays ran at 1.20 GRays/s on an H200
# against 1.07 with 256 (32: 1.21, 128: 1.19, 512: 0.87); a CPU launch ignores it
wp.set_module_options({**MODULE_OPTIONS, "block_dim": 64})

STACK_SIZE = 64
NodeStack = wp.types.vector(length=STACK_SIZE, dtype=wp.int32)
DistStack = wp.types.vector(length=STACK_SIZE, dtype=wp.float32)


@wp.func
def traverse_binary(bvh: BvhArrays, r: Ray, tmin: float, tmax: float, any_hit: bool) -> Hit:
    """`traverse` on the binary tree (bvh.nodes)."""
    hit = Hit()
    hit.t = INF
    hit.triangle = -1
    best = tmax
    root = bvh.nodes[0]
    if intersect_box(r, root.lo, root.hi, tmin, best) == INF:
        return hit
    nodes = NodeStack()
    dists = DistStack()
    sp = int(0)
    node = int(0)
    while True:
        n = bvh.nodes[node]
        if n.count > 0:
            if intersect_leaf(bvh, r, n.first, n.count, tmin, tmax, hit, any_hit):
                hit.triangle = bvh.tri_ids[hit.triangle]
                return hit
            best = wp.min(hit.t, tmax)
            node = -1
        else:
            left = bvh.nodes[n.first]
            right = bvh.nodes[n.first + 1]
            tl = intersect_box(r, left.lo, left.hi, tmin, best)
            tr = intersect_box(r, right.lo, right.hi, tmin, best)
            if tl == INF and tr == INF:
                node = -1
            elif tr == INF:
                node = n.first
            elif tl == INF:
                node = n.first + 1
            elif tl <= tr:
                node = n.first
                nodes[sp] = n.first + 1
                dists[sp] = tr
                sp += 1
            else:
                node = n.first + 1
                nodes[sp] = n.first
                dists[sp] = tl
                sp += 1
        while node < 0 and sp > 0:
            sp -= 1
            if dists[sp] <= best:
                node = nodes[sp]
        if node < 0:
            break
    return finish_hit(bvh, r, tmin, tmax, hit)


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    return 0;
#else
    return 1;
#endif
"""
)
def wide_tree_traversed() -> int:
    """1 on CPU, 0 on CUDA: a constant the compiler folds, so that a CUDA kernel holds the
    binary traversal alone. Compiled in, the wide traversal (lane by lane on CUDA) cost the
    trace kernel 255 registers and a 3 kB stack, and ran 10-30x slower than the binary one
    on an H200; the binary tree it was collapsed from is always there."""
    ...


@wp.func
def traverse(bvh: BvhArrays, r: Ray, tmin: float, tmax: float, any_hit: bool) -> Hit:
    """Closest hit in [tmin, tmax], or with `any_hit` the first hit found (no float64
    refinement, no ordering bookkeeping beyond the stack), through the wide tree where the
    BVH has one (bvh.width 4 or 8) on CPU, else the binary tree: the same hits either way
    (the triangle may differ only between hits at equal t). Pass `any_hit` as a run-time
    value (a kernel argument): with a literal True, the CPU build of a kernel ran 25-30%
    slower in our measurements (clang specialises the loop badly)."""
    if wide_tree_traversed() != 0 and bvh.width > 2:
        return traverse_wide(bvh, r, tmin, tmax, any_hit)
    return traverse_binary(bvh, r, tmin, tmax, any_hit)


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
):
    i = wp.tid()
    r = make_ray(origins[i], directions[i])
    h = traverse(bvh, r, per_ray(tmin, i), per_ray(tmax, i), find_any != 0)
    out_t[i] = h.t
    out_triangle[i] = h.triangle
    out_u[i] = h.u
    out_v[i] = h.v
