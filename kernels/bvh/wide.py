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
          [144, 160)  int32 leaf-order position of each (into tri_ids)

so coordinate k of vertex m is row 3 m + k, and the test's axis permutation (kx, ky, kz)
is a choice of rows. A last block with fewer than 4 triangles repeats its last one: a
repeated triangle hits at the same t and never replaces the first (hits replace only at a
smaller t), so no lane mask is needed. The per-triangle data is the float32 vertices
themselves: Woop's test permutes and shears them per ray, so nothing per triangle can be
precomputed without giving up its watertightness.

Collapse (`collapse`): node by node from the root, a wide node's children start as its
binary node's two children, and the inner child with the largest surface area is replaced
by its own two children until there are W (Embree, bvh_builder_sah.h: "find best child with
largest bounding box area"). That is the SAH's greedy choice: in the SAH cost of a wide
tree each wide node costs its area times one SIMD box test, so opening the child of largest
area removes the largest term (Wald, Benthin, Boulos 2008, sec. 3). A wide node's choice
depends only on its binary subtree, so subtrees are collapsed in parallel: a serial start
(`collapse_kernel`) computes the subtree sizes and plans the top breadth first down to
subtrees of at most triangles / SUBTREE_SHARE, then workers on host threads
(`collapse_subtrees`) each take a subtree, plan it breadth first, take its node and block
numbers from shared counters and write it while its binary nodes are in the cache, leaf
blocks included. Numbering: a node's children are consecutive and after it (refit relies
on the latter); the top comes first, then the subtrees in the order they were finished.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import warp as wp

from ..core.atomics import shared_add, shared_max
from ..core.box import INF, half_area
from ..core.compile_options import MODULE_OPTIONS
from ..core.launch import host_pool
from ..core.mesh import triangle_corners
from ..pool.worker import launch_workers
from .node import BvhArrays, BvhNode

wp.set_module_options(MODULE_OPTIONS)

WIDTHS = (2, 4, 8)  # 2: the binary tree itself, traversed as before
# The layout (module docstring) in numbers: their one source, for Python and native code.
# A wide node's rows, W words each: lo and hi of axis a in rows 2a and 2a + 1, then these.
ROW_CHILD = wp.constant(6)
ROW_COUNT = wp.constant(7)
WORDS_PER_LANE = wp.constant(ROW_COUNT + 1)  # 8 rows: lo_x hi_x lo_y hi_y lo_z hi_z child count
# A leaf block's rows, BLOCK words each: coordinate a of vertex m in row 3m + a, then this.
BLOCK = wp.constant(4)  # triangles per leaf block
ROW_POSITION = wp.constant(9)  # the triangles' leaf-order positions (int32)
BLOCK_WORDS = wp.constant((ROW_POSITION + 1) * BLOCK)  # 40: 9 coordinate rows, 1 position row
# A binary subtree of at most MERGE triangles becomes one wide leaf (its triangles are
# contiguous in leaf order): one block test instead of a visit per binary leaf, as tinybvh
# combines leaves to 4 triangles before its BVH8_CPU conversion (CombineLeafs(4)).
MERGE = wp.constant(4)
# A CPU build for a wide tree leaves SAH ranges of at most WHOLE triangles uncut: the cuts
# below MERGE are thrown away by the collapse, and each cost a sort and two sweeps (4M
# gallery, one worker: -5%). WHOLE = 3 rather than MERGE: the binary tree's SAH cost
# (leaves counted per triangle) rises 0.8% (4M gallery) where 4 took it up 2.8%; the wide
# tree is the same either way, but for the order of a leaf block's triangles.
WHOLE = 3
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
# The constants native code reads the layout with (bvh/wide_simd.h), by their names here.
NATIVE_LAYOUT = {
    "ROW_CHILD": ROW_CHILD, "ROW_COUNT": ROW_COUNT, "WORDS_PER_LANE": WORDS_PER_LANE,
    "MAX_WIDTH": MAX_WIDTH, "BLOCK": BLOCK, "ROW_POSITION": ROW_POSITION,
    "BLOCK_WORDS": BLOCK_WORDS, "WIDE_STACK": WIDE_STACK,
}


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


@wp.func_native(
    """
#if !defined(__CUDA_ARCH__)
    const char* p = (const char*)&tri_ids.data[first];
    const char* end = (const char*)&tri_ids.data[first + count];
    for (; p < end; p += 64) __builtin_prefetch(p);
#endif
"""
)
def prefetch_leaf_ids(tri_ids: wp.array(dtype=int), first: int, count: int):
    """Start loading the triangle ids of leaf positions [first, first + count) (CPU; a
    no-op on CUDA)."""
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
def block_count(triangles: int) -> int:
    """Blocks of a leaf of this many triangles."""
    return (triangles + BLOCK - 1) / BLOCK


@wp.func
def store_lane_corners(bvh: BvhArrays, blocks: wp.array(dtype=float), base: int, i: int):
    """The corners of leaf position i, from the mesh, into the block lane whose first word
    is `base` (its coordinate rows; the build and the refit)."""
    t = triangle_corners(bvh.vertices, bvh.indices, bvh.tri_ids[i])
    for m in range(3):
        for a in range(3):
            blocks[base + (3 * m + a) * BLOCK] = t[m, a]


@wp.func
def lane_word(ref: int) -> int:
    """The first word of block lane `ref` (block * BLOCK + lane: a wide traversal's hit)."""
    return (ref / BLOCK) * BLOCK_WORDS + ref % BLOCK


@wp.func
def lane_corners(blocks: wp.array(dtype=float), ref: int) -> wp.mat33:
    """Rows: the three corners of block lane `ref` (store_lane_corners's)."""
    b = lane_word(ref)
    return wp.matrix_from_rows(
        wp.vec3(blocks[b], blocks[b + BLOCK], blocks[b + 2 * BLOCK]),
        wp.vec3(blocks[b + 3 * BLOCK], blocks[b + 4 * BLOCK], blocks[b + 5 * BLOCK]),
        wp.vec3(blocks[b + 6 * BLOCK], blocks[b + 7 * BLOCK], blocks[b + 8 * BLOCK]))


@wp.func
def lane_position(blocks: wp.array(dtype=float), ref: int) -> int:
    """The leaf-order position of block lane `ref`'s triangle."""
    return float_bits(blocks[lane_word(ref) + ROW_POSITION * BLOCK])


@wp.func
def fill_block(bvh: BvhArrays, blocks: wp.array(dtype=float), block: int, first: int, n: int):
    """Block `block`: leaf-order triangles [first, first + n) in its lanes (from the mesh),
    the last one repeated in the lanes after them."""
    for k in range(BLOCK):
        i = first + wp.min(k, n - 1)
        base = block * BLOCK_WORDS + k
        store_lane_corners(bvh, blocks, base, i)
        blocks[base + ROW_POSITION * BLOCK] = bits_float(i)


@wp.struct
class WidePlan:
    """A wide node as the collapse plans it, before the wide tree's size is known (48 bytes).
    Its children and leaf blocks are numbered within the plan's slab (`plan_node`)."""

    kids: Lanes  # 32 bytes: the binary node of each lane (greedy_children), -1 unused
    binary: int  # the binary node it is made from
    stacked: int  # most traversal stack entries held on reaching it
    first_child: int  # slab index of its first inner child (the others follow); -1: not
    # planned here (a subtree's root in the top: its worker plans it)
    first_block: int  # slab number of its first leaf block (the others follow)


# Collapse counters (one int32 array shared by the collapse's launches)
TOP_NODES = wp.constant(0)  # wide nodes of the top (planned by the serial start)
SUBTREES = wp.constant(1)  # subtrees below it, left to the workers
WIDE_NODES = wp.constant(2)  # wide nodes numbered so far (the tree's, once done) ...
LEAF_BLOCKS = wp.constant(3)  # ... and leaf blocks
MOST = wp.constant(4)  # most stack entries, over the whole tree once done
BOUND = wp.constant(5)  # 1 + the inner binary nodes that are not wide leaves: >= wide nodes
BLOCKS = wp.constant(6)  # leaf blocks of the whole tree (known before the greedy choices)
CLAIM = wp.constant(7)  # next task of the workers (subtrees, then top nodes)
COUNTERS = 8
# Subtrees of at most max(triangles / SUBTREE_SHARE, SUBTREE_MIN) triangles are collapsed by
# the workers, each planned and written at once (its binary nodes still in the cache), the
# nodes above them planned by one thread: a few hundred tasks for the shared scenes, so the
# workers' shares are even.
SUBTREE_SHARE = 256
SUBTREE_MIN = 512
MAX_WORKERS = 256  # on CUDA: each worker has a subtree's plans of its own


@wp.func
def plan_node(nodes: wp.array(dtype=BvhNode), sizes: wp.array(dtype=int),
              plans: wp.array(dtype=WidePlan), slab: int, w: int, width: int, count: int,
              blocks: int) -> wp.vec3i:
    """Plan the slab's wide node w (its binary node and stack entries set when it was
    queued): its lanes, its inner children queued in the slab from `count` on, its leaf
    blocks numbered from `blocks` on. Returns the new (count, blocks) and the stack entries
    a traversal holds at the node (all k children are pushed before the nearest is taken
    back)."""
    p = plans[slab + w]
    kids = greedy_children(nodes, sizes, p.binary, width)
    k = int(0)
    for j in range(width):
        if kids[j] >= 0:
            k += 1
    p.kids = kids
    p.first_child = count
    p.first_block = blocks
    plans[slab + w] = p
    for j in range(width):
        c = kids[j]
        if c >= 0:
            if is_wide_leaf(nodes, sizes, c):
                blocks += block_count(sizes[c])
            else:
                q = WidePlan()
                q.binary = c
                # what it held at its parent plus the parent's other hit children (at most
                # k - 1) still on the stack
                q.stacked = p.stacked + k - 1
                q.first_child = -1
                plans[slab + count] = q
                count += 1
    return wp.vec3i(count, blocks, p.stacked + k)


@wp.func
def plan_breadth_first(nodes: wp.array(dtype=BvhNode), sizes: wp.array(dtype=int),
                       plans: wp.array(dtype=WidePlan), slab: int, width: int, limit: int,
                       deferred: wp.array(dtype=int)) -> wp.vec4i:
    """Plan the wide nodes below the slab's node 0 (queued there) breadth first, except
    those (below node 0) made from binary subtrees of at most `limit` triangles: their
    slab indices are listed in `deferred`. Returns the slab's (nodes, leaf blocks, most
    stack entries, deferred)."""
    count = int(1)
    blocks = int(0)
    most = int(0)
    queued = int(0)
    w = int(0)
    while w < count:
        if w > 0 and sizes[plans[slab + w].binary] <= limit:
            deferred[queued] = w
            queued += 1
        else:
            r = plan_node(nodes, sizes, plans, slab, w, width, count, blocks)
            count = r[0]
            blocks = r[1]
            most = wp.max(most, r[2])
        w += 1
    return wp.vec4i(count, blocks, most, queued)


@wp.func
def wide_leaf_blocks(nodes: wp.array(dtype=BvhNode), sizes: wp.array(dtype=int), c: int) -> int:
    """Leaf blocks of binary node c if it is a wide leaf, else 0."""
    if is_wide_leaf(nodes, sizes, c):
        return block_count(sizes[c])
    return 0


@wp.kernel
def collapse_kernel(
    nodes: wp.array(dtype=BvhNode),
    node_count: int,
    width: int,
    limit: int,  # subtrees of at most this many triangles are left to the workers
    sizes: wp.array(dtype=int),  # out, per binary node: triangles in its subtree ...
    starts: wp.array(dtype=int),  # ... and the first one's leaf position
    top: wp.array(dtype=WidePlan),  # out: the top's plans, breadth first
    subtrees: wp.array(dtype=int),  # out: the top index of each subtree's root
    counters: wp.array(dtype=int),
):
    """The collapse's serial start (one thread): subtree sizes bottom up (a child's index is
    above its parent's), with a bound on the wide nodes and the number of leaf blocks,
    which the greedy choices do not change: the wide leaves are the wide-leaf children of
    the other inner nodes. Then the top of the wide tree planned breadth first from the
    root, down to the subtrees of at most `limit` triangles, whose roots are queued for the
    workers; the top's nodes and blocks come first in the tree."""
    bound = int(1)
    blocks = int(0)
    for i in range(node_count - 1, -1, -1):
        # the build's workers wrote the nodes on other cores: asked for well ahead, -8% here
        prefetch_node(nodes, sizes, wp.max(i - 64, 0))
        n = nodes[i]
        if n.count > 0:
            sizes[i] = n.count
            starts[i] = n.first
        else:
            sizes[i] = sizes[n.first] + sizes[n.first + 1]
            starts[i] = starts[n.first]
            if sizes[i] > MERGE:
                bound += 1
                blocks += wide_leaf_blocks(nodes, sizes, n.first)
                blocks += wide_leaf_blocks(nodes, sizes, n.first + 1)
    if is_wide_leaf(nodes, sizes, 0):  # the root's only lane
        blocks = wide_leaf_blocks(nodes, sizes, 0)
    root = WidePlan()
    root.first_child = -1
    top[0] = root
    r = plan_breadth_first(nodes, sizes, top, 0, width, limit, subtrees)
    counters[TOP_NODES] = r[0]
    counters[WIDE_NODES] = r[0]
    counters[LEAF_BLOCKS] = r[1]
    counters[MOST] = r[2]
    counters[SUBTREES] = r[3]
    counters[BOUND] = bound
    counters[BLOCKS] = blocks


@wp.func
def write_lane(wide: wp.array(dtype=float), base: int, width: int, j: int, lo: wp.vec3,
               hi: wp.vec3, child: int, count: int):
    for a in range(3):
        wide[base + (2 * a) * width + j] = lo[a]
        wide[base + (2 * a + 1) * width + j] = hi[a]
    wide[base + ROW_CHILD * width + j] = bits_float(child)
    wide[base + ROW_COUNT * width + j] = bits_float(count)


# A leaf's blocks filled on a CPU, as native code: each block's 4 lanes gathered from the
# mesh and its 10 rows stored whole (16 bytes each), not 40 single floats through Warp's
# array indexing; the same words as fill_block's. (CUDA: 0, fill_block runs.)
FILL_SOURCE = """
#if !defined(__CUDA_ARCH__)
    constexpr int LANES = BLOCK_LANES, WORDS = BLOCK_SIZE, POSITION = POSITION_ROW;
    for (int q = 0; q * LANES < count; ++q) {
        float rows[WORDS];
        const int n = count - q * LANES < LANES ? count - q * LANES : LANES;
        for (int k = 0; k < LANES; ++k) {
            const int i = first + q * LANES + (k < n - 1 ? k : n - 1);
            const int tri = tri_ids.data[i];
            for (int m = 0; m < 3; ++m) {
                const float* v = vertices.data[indices.data[tri].c[m]].c;
                for (int a = 0; a < 3; ++a)
                    rows[(3 * m + a) * LANES + k] = v[a];
            }
            __builtin_memcpy(&rows[POSITION * LANES + k], &i, sizeof(int));
        }
        __builtin_memcpy(blocks.data + (long long)(block + q) * WORDS, rows, sizeof(rows));
    }
    return 1;
#else
    return 0;
#endif
""".replace("BLOCK_LANES", str(int(BLOCK))).replace("BLOCK_SIZE", str(int(BLOCK_WORDS))).replace(
    "POSITION_ROW", str(int(ROW_POSITION)))


@wp.func_native(FILL_SOURCE)
def fill_leaf_native(vertices: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.vec3i),
                     tri_ids: wp.array(dtype=int), blocks: wp.array(dtype=float), block: int,
                     first: int, count: int) -> int:
    """The blocks from `block` of the leaf of leaf-order triangles [first, first + count)
    (FILL_SOURCE); 0 where not compiled."""
    ...


@wp.func
def fill_leaf(bvh: BvhArrays, blocks: wp.array(dtype=float), block: int, first: int,
              count: int):
    """The blocks from `block` of the leaf of leaf-order triangles [first, first + count)."""
    if fill_leaf_native(bvh.vertices, bvh.indices, bvh.tri_ids, blocks, block, first,
                        count) == 0:
        for q in range(block_count(count)):
            fill_block(bvh, blocks, block + q, first + q * BLOCK,
                       wp.min(BLOCK, count - q * BLOCK))


@wp.func
def write_node(nodes: wp.array(dtype=BvhNode), sizes: wp.array(dtype=int),
               starts: wp.array(dtype=int), bvh: BvhArrays,
               wide: wp.array(dtype=float), blocks: wp.array(dtype=float), width: int,
               k: int, p: WidePlan, child_base: int, block_base: int):
    """Wide node k from its plan, whose slab's node q is wide node child_base + q and whose
    slab's block b is block block_base + b; its leaves' blocks filled."""
    base = k * WORDS_PER_LANE * width
    child = child_base + p.first_child
    block = block_base + p.first_block
    for j in range(width):
        c = p.kids[j]
        if c < 0:
            write_lane(wide, base, width, j, wp.vec3(INF), wp.vec3(INF), 0, 0)
        else:
            n = nodes[c]
            size = sizes[c]
            if is_wide_leaf(nodes, sizes, c):
                write_lane(wide, base, width, j, n.lo, n.hi, block, size)
                fill_leaf(bvh, blocks, block, starts[c], size)
                block += block_count(size)
            else:
                write_lane(wide, base, width, j, n.lo, n.hi, child, 0)
                child += 1


@wp.kernel
def collapse_subtrees(
    nodes: wp.array(dtype=BvhNode),
    width: int,
    limit: int,
    sizes: wp.array(dtype=int),
    starts: wp.array(dtype=int),
    bvh: BvhArrays,  # the mesh and the leaf order (tri_ids) the blocks are filled from
    top: wp.array(dtype=WidePlan),
    subtrees: wp.array(dtype=int),
    plans: wp.array(dtype=WidePlan),  # `limit` per worker: its subtree's, breadth first
    wide: wp.array(dtype=float),  # out
    blocks: wp.array(dtype=float),  # out
    counters: wp.array(dtype=int),
    first_worker: int,
):
    """A worker (one per host thread on CPU) takes tasks in turn: a subtree, which it plans
    breadth first from its root (at the root's top index), then numbers (the next free
    wide nodes and blocks, taken at once) and writes; or a top node, which it writes. A
    subtree of c triangles has fewer than c wide nodes, so `limit` plans hold any."""
    slab = (first_worker + wp.tid()) * limit
    queued = counters[SUBTREES]
    total = queued + counters[TOP_NODES]
    while True:
        t = shared_add(counters, CLAIM, 1)
        if t >= total:
            break
        if t >= queued:
            p = top[t - queued]
            if p.first_child >= 0:  # not a subtree's root
                write_node(nodes, sizes, starts, bvh, wide, blocks, width, t - queued,
                           p, 0, 0)
            continue
        root = subtrees[t]
        plans[slab] = top[root]
        # its leaves' blocks are filled from this range of ids, in no order the hardware
        # prefetcher follows: loaded in order while the subtree is planned
        b = plans[slab].binary
        prefetch_leaf_ids(bvh.tri_ids, starts[b], sizes[b])
        r = plan_breadth_first(nodes, sizes, plans, slab, width, 0, subtrees)  # defers none
        count = r[0]
        shared_max(counters, MOST, r[2])
        # its node q > 0 is wide node base + q, its block b is block block_base + b
        base = shared_add(counters, WIDE_NODES, count - 1) - 1
        block_base = shared_add(counters, LEAF_BLOCKS, r[1])
        write_node(nodes, sizes, starts, bvh, wide, blocks, width, root, plans[slab],
                   base, block_base)
        for q in range(1, count):
            write_node(nodes, sizes, starts, bvh, wide, blocks, width, base + q,
                       plans[slab + q], base, block_base)


def empty_wide(width: int, device) -> wp.array:
    """The wide tree of a mesh with no triangles: a root whose lanes are all unused."""
    node = np.zeros((8, width), np.float32)
    node[:6] = np.inf
    return wp.array(node.ravel(), dtype=float, device=device)


def collapse(nodes: wp.array, node_count: int, bvh: BvhArrays, triangles: int, width: int,
             device, workers: int, alongside: Callable[[], None] = lambda: None
             ) -> tuple[wp.array, wp.array, dict]:
    """The wide tree of width 4 or 8 of a binary tree of `node_count` nodes over
    `triangles` triangles (leaf order), its leaf blocks, and its statistics (wide nodes,
    most traversal stack entries, leaf blocks). The serial start plans the top, then
    `workers` collapse the subtrees below it; the subtrees' places in the wide tree are in
    the order the workers finish them (the tree, and so every traversal, is the same).
    The blocks are filled from `bvh`'s mesh in the order of `bvh.tri_ids`; `alongside` (what
    fills `bvh.tri_ids`, which only the workers read) runs on the calling thread while the
    serial start runs on a host thread (on CPU; before it elsewhere)."""
    workers = min(workers, MAX_WORKERS)
    inner = max(node_count // 2, 1)  # a wide node is made from an inner binary node
    sizes, starts = (wp.empty(max(node_count, 1), dtype=int, device=device) for _ in range(2))
    top = wp.empty(inner, dtype=WidePlan, device=device)
    subtrees = wp.empty(inner, dtype=int, device=device)
    limit = max(triangles // SUBTREE_SHARE, SUBTREE_MIN)
    plans = wp.empty(workers * limit, dtype=WidePlan, device=device)
    counters = wp.zeros(COUNTERS, dtype=int, device=device)

    def start() -> np.ndarray:
        wp.launch(collapse_kernel, dim=1, inputs=[nodes, node_count, width, limit, sizes,
                                                  starts, top, subtrees, counters],
                  device=device)
        return counters.numpy()

    if device.is_cpu:
        started = host_pool(1).submit(start)
        alongside()
        c = started.result()
    else:
        alongside()
        c = start()
    bound, used = int(c[BOUND]), int(c[BLOCKS])
    wide = wp.empty(bound * int(WORDS_PER_LANE) * width, dtype=float, device=device)
    blocks = wp.empty(max(used, 1) * int(BLOCK_WORDS), dtype=float, device=device)
    launch_workers(collapse_subtrees, workers, [nodes, width, limit, sizes, starts, bvh,
                                                top, subtrees, plans, wide, blocks, counters],
                   device)
    c = counters.numpy()
    count, most = int(c[WIDE_NODES]), int(c[MOST])
    # a view: of the bound's pages, only the nodes' were ever touched, so only they take
    # memory (a copy took another 20 bytes per triangle at the build's peak)
    return (wide[: count * int(WORDS_PER_LANE) * width], blocks,
            {"wide_nodes": count, "wide_stack": most, "leaf_blocks": used})
