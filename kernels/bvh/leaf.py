"""What the traversals do at a binary leaf and at the end: the watertight test of a leaf's run
of triangles, and the float64 refinement of the closest hit (shared by the binary and the
wide traversal, so both report bit-identical hits). Until the end, hit.triangle is a hit
reference: on a tree traversed wide (`wide_leaves`) the block lane whose test found it
(block * BLOCK + lane), else the leaf position; `finish_hit` (or, for an any hit,
`leaf_position` and tri_ids) maps it to the caller's index. The block lane lets the finish
read the corners from the block the leaf test just read: from the mesh (three dependent
reads) the blade's closest hits took 360 ns a ray on one thread, 290 from the block."""

from __future__ import annotations

import warp as wp

from ..core.mesh import triangle_corners
from ..core.ray import Hit, Ray
from ..core.triangle import intersect_triangle, refine_hit
from .node import BvhArrays
from .wide import lane_corners, lane_position


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
def wide_leaves(bvh: BvhArrays) -> bool:
    """Whether `bvh` is traversed wide here, so that its hits are block lanes."""
    return wide_tree_traversed() != 0 and bvh.width > 2


@wp.func
def leaf_position(bvh: BvhArrays, ref: int) -> int:
    """The leaf position of hit reference `ref` (>= 0)."""
    if wide_leaves(bvh):
        return lane_position(bvh.blocks, ref)
    return ref


@wp.func
def intersect_leaf(bvh: BvhArrays, r: Ray, first: int, count: int, tmin: float,
                   tmax: float, hit: wp.ref[Hit], any_hit: bool) -> bool:
    """Test triangles [first, first + count) of leaf order in [tmin, min(tmax, hit.t)]
    (hit.t is inf until a hit); a closer hit goes into `hit` with its leaf position. With
    `any_hit`, the first hit ends the test and True is returned: the traversal is done."""
    for i in range(first, first + count):
        h = intersect_triangle(
            r, bvh.tri_verts[3 * i], bvh.tri_verts[3 * i + 1], bvh.tri_verts[3 * i + 2],
            tmin, wp.min(hit.t, tmax),
        )
        if h[0] < hit.t or (h[0] == hit.t and i < hit.triangle):  # ties: the first position
            hit.t = h[0]
            hit.u = h[1]
            hit.v = h[2]
            hit.triangle = i
            if any_hit:
                return True
    return False


@wp.func
def finish_hit(bvh: BvhArrays, r: Ray, tmin: float, tmax: float, hit: Hit) -> Hit:
    """The closest hit found (its reference in hit.triangle) refined in float64 and given
    the caller's triangle index. The corners are the block lane's on a wide tree, else the
    mesh's: the same float32 values, whichever tree found the hit."""
    if hit.triangle >= 0:
        tri = bvh.tri_ids[leaf_position(bvh, hit.triangle)]
        if wide_leaves(bvh):
            t = lane_corners(bvh.blocks, hit.triangle)
        else:
            t = triangle_corners(bvh.vertices, bvh.indices, tri)
        exact = refine_hit(r, t[0], t[1], t[2], tmin, tmax, wp.vec3(hit.t, hit.u, hit.v))
        hit.t = exact[0]
        hit.u = exact[1]
        hit.v = exact[2]
        hit.triangle = tri
    return hit


@wp.func
def leaf_order_hit(bvh: BvhArrays, r: Ray, tmin: float, tmax: float, hit: Hit,
                   stopped: bool) -> Hit:
    """The binary traversal's result as found: hit.triangle a leaf position, t unrefined
    (`finish_traversal` makes it the caller's)."""
    return hit


@wp.func
def finish_traversal(bvh: BvhArrays, r: Ray, tmin: float, tmax: float, hit: Hit,
                     any_hit: bool) -> Hit:
    """What `traverse` returns of a traversal's hit in leaf order: an any hit as found, with
    the caller's triangle index; a closest hit through `finish_hit`."""
    if any_hit:
        if hit.triangle >= 0:
            hit.triangle = bvh.tri_ids[leaf_position(bvh, hit.triangle)]
        return hit
    return finish_hit(bvh, r, tmin, tmax, hit)
