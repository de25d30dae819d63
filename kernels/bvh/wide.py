"""Wide BVH nodes (4 or 8 children) collapsed from the binary SAH tree, as Embree's BVH4/BVH8.

Layout: one flat float32 array, WORDS_PER_LANE * W words (32 bits each) per node of width W,
structure-of-arrays so that one SIMD load brings a coordinate of all W child boxes (Embree's
BVHN AABBNode, tinybvh's BVH8_CPU). Node k starts at word 8 W k (W = 8: 256 bytes, four
cache lines; W = 4: 128 bytes, two):

    bytes [ 0W,  4W)  lo_x   float32 per child lane
          [ 4W,  8W)  hi_x
          [ 8W, 12W)  lo_y
          [12W, 16W)  hi_y
          [16W, 20W)  lo_z
          [20W, 24W)  hi_z
          [24W, 28W)  child  int32: inner child: its wide node index; leaf: its first
                             triangle block (below)
          [28W, 32W)  count  int32: 0 for an inner child, > 0 for a leaf's triangles

An unused lane has the box lo = hi = (+inf, +inf, +inf), a point at infinity that no ray
enters (see node.empty_root), child 0 and count 0.

Leaves: a leaf of c triangles is ceil(c / 4) consecutive blocks of 4 triangles in
structure-of-arrays form, so that the watertight test runs on 4 triangles at once (Embree's
Triangle4). A block is BLOCK_WORDS = 40 words, 160 bytes:

    bytes [  0,  16)  v0.x of the 4 triangles   [ 48,  64) v1.x   [ 96, 112) v2.x
          [ 16,  32)  v0.y                      [ 64,  80) v1.y   [112, 128) v2.y
          [ 32,  48)  v0.z                      [ 80,  96) v1.z   [128, 144) v2.z
          [144, 160)  int32 leaf-order position of each (into tri_verts / tri_ids)

so coordinate k of vertex m is row 3 m + k, and the test's axis permutation (kx, ky, kz)
is a choice of rows. A last block with fewer than 4 triangles repeats its last one: a
repeated triangle hits at the same t and never replaces the first (hits replace only at a
smaller t), so no lane mask is needed. The per-triangle data is the float32 vertices
themselves: Woop's test permutes and shears them per ray, so nothing per triangle can be
precomputed without giving up its watertightness.

Collapse (`collapse_kernel`): node by node from the root, a wide node's children start as
its binary node's two children, and the inner child with the largest surface area is
replaced by its own two children until there are W (Embree, bvh_builder_sah.h: "find best
child with largest bounding box area"). That is the SAH's greedy choice: in the SAH cost
of a wide tree each wide node costs its area times one SIMD box test, so opening the child
of largest area removes the largest term (Wald, Benthin, Boulos 2008, sec. 3).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..core.box import INF, half_area
from ..core.launch import host_threads, launch_split
from .node import BvhNode

wp.set_module_options({"enable_backward": False, "optimization_level": 3})

WIDTHS = (2, 4, 8)  # 2: the binary tree itself, traversed as before
WORDS_PER_LANE = wp.constant(8)  # lo_x hi_x lo_y hi_y lo_z hi_z child count
BLOCK = wp.constant(4)  # triangles per leaf block
BLOCK_WORDS = wp.constant(40)  # 9 coordinate rows and 1 position row of BLOCK lanes
# A binary subtree of at most MERGE triangles becomes one wide leaf (its triangles are
# contiguous in leaf order): one block test instead of a visit per binary leaf, as tinybvh
# combines leaves to 4 triangles before its BVH8_CPU conversion (CombineLeafs(4)).
MERGE = wp.constant(4)
MAX_WIDTH = wp.constant(8)
Lanes = wp.types.vector(length=MAX_WIDTH, dtype=wp.int32)
LaneFloats = wp.types.vector(length=MAX_WIDTH, dtype=wp.float32)
# Traversal stack entries: the most a wide traversal ever holds is the tree's `wide_stack`
# statistic (computed by the collapse: 39-83 on the shared scenes, 8 wide); a tree that needs
# more is traversed as a binary tree. Each traversal zero-fills its stack (Warp initialises
# vectors), so it is no larger than that.
WIDE_STACK = 128
WideStack = wp.types.vector(length=WIDE_STACK, dtype=wp.int32)
WideDists = wp.types.vector(length=WIDE_STACK, dtype=wp.float32)


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    return __float_as_int(x);
#else
    int i;
    __builtin_memcpy(&i, &x, 4);
    return i;
#endif
"""
)
def float_bits(x: float) -> int:
    """The int32 stored in a float32 word of the node array (its bits, not its value)."""
    ...


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    return __int_as_float(i);
#else
    float x;
    __builtin_memcpy(&x, &i, 4);
    return x;
#endif
"""
)
def bits_float(i: int) -> float:
    """The float32 word whose bits are the int32 `i` (inverse of float_bits)."""
    ...


@wp.func
def is_wide_leaf(nodes: wp.array(dtype=BvhNode), sizes: wp.array(dtype=int), c: int) -> bool:
    """A binary leaf, or a subtree small enough for one block (see MERGE)."""
    return nodes[c].count > 0 or sizes[c] <= MERGE


@wp.func_native(
    """
#if !defined(__CUDA_ARCH__)
    __builtin_prefetch(&nodes.data[i]);
    __builtin_prefetch(&sizes.data[i]);
#endif
"""
)
def prefetch_node(nodes: wp.array(dtype=BvhNode), sizes: wp.array(dtype=int), i: int):
    """Start loading binary node i and its size (CPU; a no-op on CUDA)."""
    ...


@wp.func
def opening_gain(nodes: wp.array(dtype=BvhNode), sizes: wp.array(dtype=int), c: int) -> float:
    """What opening binary node c saves in SAH terms, its surface area, or -1 if c is a wide
    leaf (is_wide_leaf). The node array is far larger than the caches: the children of an
    inner c, which opening it would read next, are prefetched."""
    n = nodes[c]
    if n.count > 0 or sizes[c] <= MERGE:
        return -1.0
    prefetch_node(nodes, sizes, n.first)
    return half_area(n.lo, n.hi)


@wp.func
def greedy_children(nodes: wp.array(dtype=BvhNode), sizes: wp.array(dtype=int), b: int,
                    width: int) -> Lanes:
    """The binary nodes that become the children of the wide node made from binary node b:
    its two children, then the inner child of largest area opened until there are `width`
    (the SAH's greedy choice, module docstring). Unused lanes hold -1. A tree that is one
    leaf is its root's only child. Each candidate's area is computed once, when it joins:
    the node array is far larger than the caches, so its loads are what this costs."""
    kids = Lanes()
    for j in range(MAX_WIDTH):
        kids[j] = -1
    if is_wide_leaf(nodes, sizes, b):
        kids[0] = b
        return kids
    gain = LaneFloats()
    left = nodes[b].first
    kids[0] = left
    kids[1] = left + 1
    gain[0] = opening_gain(nodes, sizes, left)
    gain[1] = opening_gain(nodes, sizes, left + 1)
    k = int(2)
    while k < width:
        best = int(0)
        for j in range(1, k):
            if gain[j] > gain[best]:
                best = j
        if gain[best] < 0.0:
            break
        left = nodes[kids[best]].first
        kids[best] = left
        kids[k] = left + 1
        gain[best] = opening_gain(nodes, sizes, left)
        gain[k] = opening_gain(nodes, sizes, left + 1)
        k += 1
    return kids


@wp.func
def write_lane(wide: wp.array(dtype=float), base: int, width: int, j: int, lo: wp.vec3,
               hi: wp.vec3, child: int, count: int):
    for a in range(3):
        wide[base + (2 * a) * width + j] = lo[a]
        wide[base + (2 * a + 1) * width + j] = hi[a]
    wide[base + 6 * width + j] = bits_float(child)
    wide[base + 7 * width + j] = bits_float(count)


@wp.kernel
def fill_blocks(tri_verts: wp.array(dtype=wp.vec3), block_triangles: wp.array(dtype=wp.vec3i),
                blocks: wp.array(dtype=float)):
    """Block (block, first, n): leaf-order triangles [first, first + n) in its lanes, the
    last one repeated in the lanes after them."""
    b = block_triangles[wp.tid()]
    for k in range(BLOCK):
        i = b[1] + wp.min(k, b[2] - 1)
        base = b[0] * BLOCK_WORDS + k
        for m in range(3):
            v = tri_verts[3 * i + m]
            for a in range(3):
                blocks[base + (3 * m + a) * BLOCK] = v[a]
        blocks[base + 9 * BLOCK] = bits_float(i)


@wp.kernel
def collapse_kernel(
    nodes: wp.array(dtype=BvhNode),
    node_count: int,
    width: int,
    wide: wp.array(dtype=float),
    block_triangles: wp.array(dtype=wp.vec3i),  # out: per leaf block (block, first, n)
    sizes: wp.array(dtype=int),  # per binary node: triangles in its subtree ...
    starts: wp.array(dtype=int),  # ... and the first one's leaf position
    todo: wp.array(dtype=int),  # per wide node: the binary node it is made from
    stacked: wp.array(dtype=int),  # per wide node: most stack entries held on reaching it
    counters: wp.array(dtype=int),  # out: [wide nodes, stack entries needed, blocks]
):
    """One thread: subtree sizes bottom up (a child's index is above its parent's), then the
    wide nodes top down in breadth-first order: a wide node's children get consecutive
    indices, so the children of a node lie side by side in memory. The leaves' blocks are
    listed here and filled by `fill_blocks`, in parallel."""
    for i in range(node_count - 1, -1, -1):
        n = nodes[i]
        if n.count > 0:
            sizes[i] = n.count
            starts[i] = n.first
        else:
            sizes[i] = sizes[n.first] + sizes[n.first + 1]
            starts[i] = starts[n.first]
    todo[0] = 0
    stacked[0] = 0
    count = int(1)
    most = int(0)
    used = int(0)  # leaf blocks
    w = int(0)
    while w < count:
        kids = greedy_children(nodes, sizes, todo[w], width)
        k = int(0)
        base = w * WORDS_PER_LANE * width
        for j in range(width):
            if kids[j] >= 0:
                k += 1
        for j in range(width):
            c = kids[j]
            if c < 0:
                write_lane(wide, base, width, j, wp.vec3(INF), wp.vec3(INF), 0, 0)
            else:
                n = nodes[c]
                if is_wide_leaf(nodes, sizes, c):
                    write_lane(wide, base, width, j, n.lo, n.hi, used, sizes[c])
                    for q in range((sizes[c] + BLOCK - 1) / BLOCK):
                        block_triangles[used] = wp.vec3i(used, starts[c] + q * BLOCK,
                                                         wp.min(BLOCK, sizes[c] - q * BLOCK))
                        used += 1
                else:
                    write_lane(wide, base, width, j, n.lo, n.hi, count, 0)
                    todo[count] = c
                    # A traversal at this node holds what it held at its parent plus the
                    # parent's other hit children (at most k - 1) still on the stack.
                    stacked[count] = stacked[w] + k - 1
                    count += 1
        # at w, all k children are pushed before the nearest is taken back
        most = wp.max(most, stacked[w] + k)
        w += 1
    counters[0] = count
    counters[1] = most
    counters[2] = used


def empty_wide(width: int, device) -> wp.array:
    """The wide tree of a mesh with no triangles: a root whose lanes are all unused."""
    node = np.zeros((8, width), np.float32)
    node[:6] = np.inf
    return wp.array(node.ravel(), dtype=float, device=device)


def collapse(nodes: wp.array, node_count: int, tri_verts: wp.array, triangles: int, width: int,
             device) -> tuple[wp.array, wp.array, dict]:
    """The wide tree of width 4 or 8 of a binary tree of `node_count` nodes over
    `triangles` triangles (leaf order), its leaf blocks, and its statistics (wide nodes,
    most traversal stack entries, leaf blocks)."""
    wide = wp.empty(max(node_count, 1) * 8 * width, dtype=float, device=device)
    # every leaf holds a triangle, so a block per triangle is enough
    block_triangles = wp.empty(max(triangles, 1), dtype=wp.vec3i, device=device)
    sizes, starts, todo, stacked = (wp.empty(max(node_count, 1), dtype=int, device=device)
                                    for _ in range(4))
    counters = wp.zeros(3, dtype=int, device=device)
    wp.launch(collapse_kernel, dim=1,
              inputs=[nodes, node_count, width, wide, block_triangles, sizes, starts, todo,
                      stacked, counters], device=device)
    count, most, used = (int(x) for x in counters.numpy())
    blocks = wp.empty(max(used, 1) * int(BLOCK_WORDS), dtype=float, device=device)
    launch_split(fill_blocks, used, [tri_verts], [block_triangles[:used]], [], [blocks], device,
                 host_threads(device, None))
    return (wide[: count * 8 * width], blocks,
            {"wide_nodes": count, "wide_stack": most, "leaf_blocks": used})
