"""The BVH build's task record and data arrays (2012 paper, sec. 4), shared by its phases.

One `BuildTask` per pool slot; `BuildData` holds the index array of `BuildItem`s (each
position's triangle with its box), the arrays of the PPS, Swap and AABB phases, the SAH bins
and the nodes.
"""

from __future__ import annotations

import warp as wp

from .node import BvhNode

BINS = wp.constant(32)  # SAH bins on the split axis (sec. 4.1), per pool slot and worker
BinFloats = wp.types.vector(length=BINS, dtype=wp.float32)  # a value per bin

METHOD_MEDIAN = wp.constant(0)
METHOD_SAH = wp.constant(1)

PHASE_SPLIT_PLANE = wp.constant(0)
PHASE_PPS = wp.constant(1)
PHASE_SWAP = wp.constant(2)
PHASE_AABB = wp.constant(3)
PHASE_DONE = wp.constant(4)
# cycles per phase; "Nodes": writing nodes, storing child tasks and small subtrees
PHASE_NAMES = ("SplitPlane", "PPS", "Swap", "AABB", "Nodes")

# counters[]
NODE_COUNT = wp.constant(0)
MAX_DEPTH = wp.constant(1)

SMALL_TASK = wp.constant(64)  # SAH ranges up to this size are built in one worker
# Swap's steps: 0 gather and 1 exchange (through the spare array, in parallel chunks); or,
# for a task of at most BuildData.serial_max triangles, the same exchange by one worker in
# one pass over the range (build.exchange_in_place)
SWAP_IN_PLACE = wp.constant(2)
SmallFloats = wp.types.vector(length=SMALL_TASK, dtype=wp.float32)  # per item of a range
SmallInts = wp.types.vector(length=SMALL_TASK, dtype=wp.int32)  # the small subtree's stack
SUBTREE_NODES = wp.constant(2 * SMALL_TASK - 1)  # the most nodes a small subtree has


@wp.struct
class BuildTask:
    node: int  # the node this task fills
    start: int  # triangle range [start, start + count) of the index array
    count: int
    depth: int
    phase: int
    step: int
    chunks: int  # work chunks of the current step
    lo: wp.vec3  # node box
    hi: wp.vec3
    clo: wp.vec3  # centroid box: the split axis, SAH bins and median plane live in it
    chi: wp.vec3
    axis: int
    split_bin: int  # SAH: bins <= split_bin go left
    split: float  # median: centroids <= split go left
    pivot: int  # triangles that go left
    ones_left: int  # right-marked triangles in [start, start + pivot): what Swap exchanges
    llo: wp.vec3  # children's boxes and centroid boxes (the latter for median only)
    lhi: wp.vec3
    lclo: wp.vec3
    lchi: wp.vec3
    rlo: wp.vec3
    rhi: wp.vec3
    rclo: wp.vec3
    rchi: wp.vec3


@wp.struct
class BuildItem:
    """A position of the index array: a triangle and its box, which move together, so that
    every phase reads memory in order (the centroid is the box's middle). 28 bytes."""

    lo: wp.vec3
    tri: int  # the caller's triangle index
    hi: wp.vec3


@wp.struct
class BuildData:
    items: wp.array(dtype=BuildItem)  # the index array, in leaf order when done
    spare: wp.array(dtype=BuildItem)  # Swap's separate index array ...
    spare_pos: wp.array(dtype=int)  # ... and where each of its entries came from
    mark: wp.array(dtype=wp.int8)  # 1 = right of the plane, per index-array position
    scan: wp.array(dtype=int)  # PPS levels, stored inside each task's own range
    box_lo: wp.array(dtype=wp.vec3)  # AABB levels, likewise
    box_hi: wp.array(dtype=wp.vec3)
    cbox_lo: wp.array(dtype=wp.vec3)  # ... and of the centroids' boxes
    cbox_hi: wp.array(dtype=wp.vec3)
    bin_count: wp.array(dtype=int)  # BINS per pool slot, then per worker (from worker_bins)
    bin_lo: wp.array(dtype=wp.vec3)  # box of the bin's triangles
    bin_hi: wp.array(dtype=wp.vec3)
    bin_clo: wp.array(dtype=wp.vec3)  # box of their centroids
    bin_chi: wp.array(dtype=wp.vec3)
    tasks: wp.array(dtype=BuildTask)  # the task data array, one entry per pool slot
    nodes: wp.array(dtype=BvhNode)
    # SUBTREE_NODES per worker: a small subtree's nodes until they take their numbers in
    # `nodes` all at once (sweep_sah.number_subtree)
    subtree_nodes: wp.array(dtype=BvhNode)
    counters: wp.array(dtype=int)
    phase_cycles: wp.array(dtype=wp.int64)  # per worker and phase (pool.worker.CYCLE_ROW)
    worker_bins: int  # the first worker's bins: after the pool slots' (the pool's capacity)
    method: int
    leaf_size: int
    max_depth: int
    serial_max: int  # SAH tasks of at most this many triangles skip PPS: SWAP_IN_PLACE
    whole_max: int  # SAH ranges of at most this many triangles are leaves, never cut


@wp.func
def centroid(it: BuildItem) -> wp.vec3:
    """The centroid of an item's triangle box (as build.triangle_box computes it)."""
    return 0.5 * (it.lo + it.hi)


@wp.func
def write_node(nodes: wp.array(dtype=BvhNode), node: int, lo: wp.vec3, hi: wp.vec3, first: int,
               count: int):
    n = BvhNode()
    n.lo = lo
    n.hi = hi
    n.first = first
    n.count = count
    nodes[node] = n


@wp.func
def write_node_box(nodes: wp.array(dtype=BvhNode), node: int, box: wp.mat33, first: int,
                   count: int):
    write_node(nodes, node, box[0], box[1], first, count)
