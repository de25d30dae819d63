"""BVH construction on the task pool (2012 paper, sec. 4).

One task per node under construction, one persistent launch for the whole build. The phases
are the paper's (sec. 4.1):
  SplitPlane  binned SAH: 32 bins on each of the three axes (the spatial median plane is
              chosen when the task is stored, so median tasks start at PPS)
  PPS         32-ary up-sweep/down-sweep prefix sum of the 'right of the plane' marks
  Swap        two steps: gather the left-marked triangles of the right part into a separate
              index array, then swap them with the right-marked ones of the left part
  AABB        reduction of the two children's boxes (median only: SAH bins give the boxes)
A work chunk is CHUNK consecutive items; a step with fewer than K chunks runs inline in the
worker that finished the previous step (sec. 3.4). A split that leaves one side empty
(coincident centroids) falls back to halving the range, and takes its boxes from AABB.
SAH nodes of at most SMALL_TASK triangles are not tasks: the worker that makes one builds
its subtree in place with exact SAH sweeps (small_subtree), leaves where they are cheaper.
"""

from __future__ import annotations

import warp as wp

from .chunks import CHUNK, ceil_div, level_base, level_count, level_size
from .geometry import INF, max3, min3
from .pool import (
    Pool,
    cycles,
    pool_acquire,
    pool_alloc,
    pool_finish,
    pool_hand_over,
    pool_idle,
    pool_publish,
    pool_release,
    pool_running,
    shared_add,
    shared_max,
    shared_max_vec3,
    shared_min_vec3,
)

wp.set_module_options({"enable_backward": False, "optimization_level": 3})

BINS = wp.constant(32)  # SAH candidate planes per axis (sec. 4.1)
BIN_SLOTS = 32  # bins per pool slot
BinFloats = wp.types.vector(length=32, dtype=wp.float32)

METHOD_MEDIAN = wp.constant(0)
METHOD_SAH = wp.constant(1)

PHASE_SPLIT_PLANE = wp.constant(0)
PHASE_PPS = wp.constant(1)
PHASE_SWAP = wp.constant(2)
PHASE_AABB = wp.constant(3)
PHASE_DONE = wp.constant(4)
# cycles per phase; "Nodes": writing nodes, storing child tasks and small subtrees
PHASE_NAMES = ("SplitPlane", "PPS", "Swap", "AABB", "Nodes")
CYCLE_ROW = wp.constant(8)  # int64 per worker in phase_cycles: a cache line, no false sharing

# counters[]
NODE_COUNT = wp.constant(0)
MAX_DEPTH = wp.constant(1)


@wp.struct
class BvhNode:
    """32 bytes. Inner nodes: children at `first` and `first + 1`, `count` 0."""

    lo: wp.vec3  # 12 bytes
    first: int  # 4: leaf: first triangle position in leaf order; inner: left child index
    hi: wp.vec3  # 12
    count: int  # 4: leaf: triangles (> 0); inner: 0


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
class BuildData:
    perm: wp.array(dtype=int)  # the index array: triangle ids, in leaf order when done
    tri_lo: wp.array(dtype=wp.vec3)  # each position's triangle box: it moves with `perm`, so
    tri_hi: wp.array(dtype=wp.vec3)  # every phase reads memory in order (centroid: its middle)
    swap_id: wp.array(dtype=int)  # Swap's separate index array (with the same payload) ...
    swap_lo: wp.array(dtype=wp.vec3)
    swap_hi: wp.array(dtype=wp.vec3)
    swap_pos: wp.array(dtype=int)  # ... and where each of its entries came from
    mark: wp.array(dtype=wp.int8)  # 1 = right of the plane, per index-array position
    scan: wp.array(dtype=int)  # PPS levels, stored inside each task's own range
    box_lo: wp.array(dtype=wp.vec3)  # AABB levels, likewise
    box_hi: wp.array(dtype=wp.vec3)
    cbox_lo: wp.array(dtype=wp.vec3)
    cbox_hi: wp.array(dtype=wp.vec3)
    bin_count: wp.array(dtype=int)  # BIN_SLOTS per pool slot, then per worker
    bin_lo: wp.array(dtype=wp.vec3)  # box of the bin's triangles
    bin_hi: wp.array(dtype=wp.vec3)
    bin_clo: wp.array(dtype=wp.vec3)  # box of their centroids
    bin_chi: wp.array(dtype=wp.vec3)
    tasks: wp.array(dtype=BuildTask)  # the task data array, one entry per pool slot
    nodes: wp.array(dtype=BvhNode)
    counters: wp.array(dtype=int)
    phase_cycles: wp.array(dtype=wp.int64)  # per worker and phase
    method: int
    leaf_size: int
    max_depth: int


# ---------------------------------------------------------------- small helpers


@wp.func
def longest_axis(lo: wp.vec3, hi: wp.vec3) -> int:
    e = hi - lo
    axis = int(0)
    if e[1] > e[axis]:
        axis = 1
    if e[2] > e[axis]:
        axis = 2
    return axis


@wp.func
def half_area(lo: wp.vec3, hi: wp.vec3) -> float:
    e = max3(hi - lo, wp.vec3(0.0))
    return e[0] * e[1] + e[1] * e[2] + e[2] * e[0]


@wp.func
def centroid(b: BuildData, i: int) -> wp.vec3:
    """The centroid of the triangle box at index-array position i (as triangle_boxes has it)."""
    return 0.5 * (b.tri_lo[i] + b.tri_hi[i])


@wp.func
def bin_scale(t: BuildTask) -> float:
    """Bins per unit length along the split axis of the task's centroid box."""
    return float(BINS) / (t.chi[t.axis] - t.clo[t.axis])


@wp.func
def bin_of(c: float, lo: float, scale: float) -> int:
    """SAH bin of a centroid coordinate: the same float expression in SplitPlane and PPS."""
    return wp.clamp(int((c - lo) * scale), 0, BINS - 1)


@wp.func
def goes_right(b: BuildData, t: BuildTask, scale: float, i: int) -> bool:
    """Marked 1 in PPS: right of the SAH plane (`scale` from bin_scale) or the median."""
    c = 0.5 * (b.tri_lo[i][t.axis] + b.tri_hi[i][t.axis])
    if b.method == METHOD_SAH:
        return bin_of(c, t.clo[t.axis], scale) > t.split_bin
    return c > t.split


# ---------------------------------------------------------------- SplitPlane


@wp.func
def split_plane_chunk(b: BuildData, t: BuildTask, bin_slot: int, chunk: int):
    """Bin one chunk's triangles into the 32 bins of the split axis (sec. 4.1, SplitPlane),
    bins that only this worker writes (plain updates). The bins span the centroid box on
    its longest axis and keep both the triangles' box and their centroids' box, which give
    the children's boxes and the next level's bins."""
    first = t.start + chunk * CHUNK
    last = wp.min(first + CHUNK, t.start + t.count)
    scale = bin_scale(t)
    origin = t.clo[t.axis]
    base = bin_slot * BIN_SLOTS
    for i in range(first, last):
        lo = b.tri_lo[i]
        hi = b.tri_hi[i]
        c = 0.5 * (lo + hi)
        k = base + bin_of(c[t.axis], origin, scale)
        b.bin_count[k] = b.bin_count[k] + 1
        b.bin_lo[k] = min3(b.bin_lo[k], lo)
        b.bin_hi[k] = max3(b.bin_hi[k], hi)
        b.bin_clo[k] = min3(b.bin_clo[k], c)
        b.bin_chi[k] = max3(b.bin_chi[k], c)


@wp.func
def reset_bin(b: BuildData, k: int):
    b.bin_count[k] = 0
    b.bin_lo[k] = wp.vec3(INF)
    b.bin_hi[k] = wp.vec3(-INF)
    b.bin_clo[k] = wp.vec3(INF)
    b.bin_chi[k] = wp.vec3(-INF)


@wp.func
def merge_bins(b: BuildData, from_slot: int, to_slot: int):
    """Add a worker's private bins to the task's shared ones (atomically: other workers
    may merge theirs at the same time) and clear them."""
    src = from_slot * BIN_SLOTS
    dst = to_slot * BIN_SLOTS
    for k in range(BIN_SLOTS):
        n = b.bin_count[src + k]
        if n > 0:
            shared_add(b.bin_count, dst + k, n)
            shared_min_vec3(b.bin_lo, dst + k, b.bin_lo[src + k])
            shared_max_vec3(b.bin_hi, dst + k, b.bin_hi[src + k])
            shared_min_vec3(b.bin_clo, dst + k, b.bin_clo[src + k])
            shared_max_vec3(b.bin_chi, dst + k, b.bin_chi[src + k])
            reset_bin(b, src + k)


@wp.func
def choose_sah_split(b: BuildData, t: BuildTask, slot: int) -> BuildTask:
    """The last finisher of SplitPlane picks the cheapest of the 31 planes with a suffix and
    a prefix sweep over the bins; the bins give the children's exact boxes and centroid
    boxes. Leaves the bins cleared for the slot's next task."""
    best_cost = float(INF)
    base = slot * BIN_SLOTS
    right_area = BinFloats()
    lo = wp.vec3(INF)
    hi = wp.vec3(-INF)
    for k in range(BINS - 1, 0, -1):  # right_area[k]: bins k .. BINS-1
        if b.bin_count[base + k] > 0:
            lo = min3(lo, b.bin_lo[base + k])
            hi = max3(hi, b.bin_hi[base + k])
        right_area[k] = half_area(lo, hi)
    lo = wp.vec3(INF)
    hi = wp.vec3(-INF)
    n_left = int(0)
    for k in range(BINS - 1):  # the plane between bins k and k + 1
        n = b.bin_count[base + k]
        if n > 0:
            n_left += n
            lo = min3(lo, b.bin_lo[base + k])
            hi = max3(hi, b.bin_hi[base + k])
        n_right = t.count - n_left
        if n_left > 0 and n_right > 0:
            cost = float(n_left) * half_area(lo, hi) + float(n_right) * right_area[k + 1]
            if cost < best_cost:
                best_cost = cost
                t.split_bin = k
                t.pivot = n_left
    t.llo = wp.vec3(INF)
    t.lhi = wp.vec3(-INF)
    t.lclo = wp.vec3(INF)
    t.lchi = wp.vec3(-INF)
    t.rlo = wp.vec3(INF)
    t.rhi = wp.vec3(-INF)
    t.rclo = wp.vec3(INF)
    t.rchi = wp.vec3(-INF)
    for k in range(BINS):
        i = base + k
        if b.bin_count[i] > 0:
            if k <= t.split_bin:
                t.llo = min3(t.llo, b.bin_lo[i])
                t.lhi = max3(t.lhi, b.bin_hi[i])
                t.lclo = min3(t.lclo, b.bin_clo[i])
                t.lchi = max3(t.lchi, b.bin_chi[i])
            else:
                t.rlo = min3(t.rlo, b.bin_lo[i])
                t.rhi = max3(t.rhi, b.bin_hi[i])
                t.rclo = min3(t.rclo, b.bin_clo[i])
                t.rchi = max3(t.rchi, b.bin_chi[i])
            reset_bin(b, i)
    if best_cost == INF:
        t.pivot = -1  # all centroids fell into one bin
    return t


# ---------------------------------------------------------------- small ranges (SAH leaves)

SMALL_TASK = wp.constant(64)  # SAH ranges up to this size are built in one worker
SmallFloats = wp.types.vector(length=64, dtype=wp.float32)  # per item of a small range
SmallInts = wp.types.vector(length=64, dtype=wp.int32)  # the small subtree's stack


@wp.func
def write_node(b: BuildData, node: int, lo: wp.vec3, hi: wp.vec3, first: int, count: int):
    n = BvhNode()
    n.lo = lo
    n.hi = hi
    n.first = first
    n.count = count
    b.nodes[node] = n


@wp.func
def write_node_box(b: BuildData, node: int, box: wp.mat33, first: int, count: int):
    write_node(b, node, box[0], box[1], first, count)


@wp.func
def sort_small(b: BuildData, start: int, count: int, axis: int):
    """Sort a small range by centroid on `axis`: an insertion sort of (key, position) pairs
    held locally, then one pass through Swap's arrays (free here: the range is this
    worker's) to move the items and their boxes."""
    keys = SmallFloats()
    order = SmallInts()
    for i in range(count):
        key = b.tri_lo[start + i][axis] + b.tri_hi[start + i][axis]
        j = i
        while j > 0:
            if keys[j - 1] <= key:
                break
            keys[j] = keys[j - 1]
            order[j] = order[j - 1]
            j -= 1
        keys[j] = key
        order[j] = start + i
    for i in range(count):
        src = order[i]
        b.swap_id[start + i] = b.perm[src]
        b.swap_lo[start + i] = b.tri_lo[src]
        b.swap_hi[start + i] = b.tri_hi[src]
    for i in range(start, start + count):
        b.perm[i] = b.swap_id[i]
        b.tri_lo[i] = b.swap_lo[i]
        b.tri_hi[i] = b.swap_hi[i]


@wp.func
def small_split(b: BuildData, start: int, count: int, area: float, may_leaf: bool) -> int:
    """Exact SAH over the count - 1 planes of a sorted small range: the size of the left
    part, or 0 where a leaf is allowed and cheaper (traversal and intersection cost 1)."""
    right_area = SmallFloats()
    lo = wp.vec3(INF)
    hi = wp.vec3(-INF)
    for k in range(count - 1, 0, -1):  # right_area[k]: items k .. count - 1
        lo = min3(lo, b.tri_lo[start + k])
        hi = max3(hi, b.tri_hi[start + k])
        right_area[k] = half_area(lo, hi)
    best = wp.where(may_leaf, area * float(count), INF)
    best_k = int(0)
    lo = wp.vec3(INF)
    hi = wp.vec3(-INF)
    for k in range(1, count):
        lo = min3(lo, b.tri_lo[start + k - 1])
        hi = max3(hi, b.tri_hi[start + k - 1])
        cost = area + half_area(lo, hi) * float(k) + right_area[k] * float(count - k)
        if cost < best:
            best = cost
            best_k = k
    return best_k


@wp.func
def range_box(b: BuildData, start: int, count: int) -> wp.mat33:
    """Rows: the box of a range's triangles and its centroids' extent."""
    lo = wp.vec3(INF)
    hi = wp.vec3(-INF)
    clo = wp.vec3(INF)
    chi = wp.vec3(-INF)
    for i in range(start, start + count):
        lo = min3(lo, b.tri_lo[i])
        hi = max3(hi, b.tri_hi[i])
        c = b.tri_lo[i] + b.tri_hi[i]  # twice the centroid: only the longest axis matters
        clo = min3(clo, c)
        chi = max3(chi, c)
    return wp.matrix_from_rows(lo, hi, chi - clo)


@wp.func
def centroid_axis(extent: wp.vec3) -> int:
    """The longest axis of a centroid box's extent, or -1 where the centroids coincide."""
    axis = longest_axis(wp.vec3(0.0), extent)
    return wp.where(extent[axis] > 0.0, axis, -1)


@wp.func
def small_subtree(b: BuildData, node: int, depth: int):
    """Finish the subtree of a node written as a leaf. SAH: a range of at most SMALL_TASK
    triangles is built here, in the worker that made it, where the pool's phases would cost
    more than the work: each node is sorted on its longest centroid axis (unless its parent
    already sorted it so) and cut at the exact SAH minimum over all count - 1 planes, and
    becomes a leaf wherever that is cheaper (leaf_size is then a maximum, as in Embree).
    Median: the node stays a leaf."""
    if b.method != METHOD_SAH:
        return
    n = b.nodes[node]
    nodes = SmallInts()  # the stack: node, depth, split axis, axis the range is sorted by
    depths = SmallInts()
    axes = SmallInts()
    sorted_by = SmallInts()
    nodes[0] = node
    depths[0] = depth
    axes[0] = centroid_axis(range_box(b, n.first, n.count)[2])
    sorted_by[0] = -1
    sp = int(1)
    deepest = depth
    while sp > 0:
        sp -= 1
        n = b.nodes[nodes[sp]]
        d = depths[sp]
        axis = axes[sp]
        deepest = wp.max(deepest, d)
        if n.count < 2 or d >= b.max_depth - 1:
            continue
        k = n.count / 2  # coincident centroids: halve, as the pool's tasks do
        if axis >= 0:
            if sorted_by[sp] != axis:
                sort_small(b, n.first, n.count, axis)
            k = small_split(b, n.first, n.count, half_area(n.lo, n.hi),
                            n.count <= b.leaf_size)
        elif n.count <= b.leaf_size:
            k = 0
        if k == 0:
            continue
        left = shared_add(b.counters, NODE_COUNT, 2)
        write_node(b, nodes[sp], n.lo, n.hi, left, 0)
        lbox = range_box(b, n.first, k)
        rbox = range_box(b, n.first + k, n.count - k)
        write_node_box(b, left, lbox, n.first, k)
        write_node_box(b, left + 1, rbox, n.first + k, n.count - k)
        nodes[sp] = left
        axes[sp] = centroid_axis(lbox[2])
        nodes[sp + 1] = left + 1
        axes[sp + 1] = centroid_axis(rbox[2])
        for c in range(2):
            depths[sp + c] = d + 1
            sorted_by[sp + c] = axis
        sp += 2
    shared_max(b.counters, MAX_DEPTH, deepest)


# ---------------------------------------------------------------- PPS


@wp.func
def pps_up_chunk(b: BuildData, t: BuildTask, level: int, chunk: int):
    """Up-sweep: level 1 marks a chunk's triangles and counts the right ones; higher levels sum
    CHUNK values of the level below."""
    dst = level_base(t.start, t.count, level) + chunk
    total = int(0)
    if level == 1:
        first = t.start + chunk * CHUNK
        last = wp.min(first + CHUNK, t.start + t.count)
        scale = float(0.0)
        if b.method == METHOD_SAH:
            scale = bin_scale(t)
        for i in range(first, last):
            right = int(0)
            if goes_right(b, t, scale, i):
                right = 1
            b.mark[i] = wp.int8(right)
            total += right
    else:
        src = level_base(t.start, t.count, level - 1)
        n = level_size(t.count, level - 1)
        first = chunk * CHUNK
        last = wp.min(first + CHUNK, n)
        for i in range(first, last):
            total += b.scan[src + i]
    b.scan[dst] = total


@wp.func
def pps_down_chunk(b: BuildData, t: BuildTask, level: int, chunk: int):
    """Down-sweep: turn CHUNK sums of `level` into exclusive prefix sums, starting from the
    offset that the level above now holds for this group."""
    src = level_base(t.start, t.count, level)
    n = level_size(t.count, level)
    running = b.scan[level_base(t.start, t.count, level + 1) + chunk]
    first = chunk * CHUNK
    last = wp.min(first + CHUNK, n)
    for i in range(first, last):
        x = b.scan[src + i]
        b.scan[src + i] = running
        running += x


@wp.func
def ones_before(b: BuildData, t: BuildTask, local: int) -> int:
    """Right-marked triangles before local position `local`, from the PPS result."""
    c = local / CHUNK
    ones = int(0)
    if c < level_size(t.count, 1):
        ones = b.scan[t.start + c]
    for i in range(t.start + c * CHUNK, t.start + local):
        ones += int(b.mark[i])
    return ones


# ---------------------------------------------------------------- Swap


@wp.func
def swap_gather_chunk(b: BuildData, t: BuildTask, chunk: int):
    """Swap, step 1: left-marked triangles right of the pivot go to the separate index array,
    ranked among themselves."""
    c = t.pivot / CHUNK + chunk
    ones = b.scan[t.start + c]
    zeros_left = t.pivot - t.ones_left
    first = c * CHUNK
    last = wp.min(first + CHUNK, t.count)
    for k in range(first, last):
        if b.mark[t.start + k] != wp.int8(0):
            ones += 1
        elif k >= t.pivot:
            r = t.start + (k - ones) - zeros_left
            i = t.start + k
            b.swap_id[r] = b.perm[i]
            b.swap_lo[r] = b.tri_lo[i]
            b.swap_hi[r] = b.tri_hi[i]
            b.swap_pos[r] = i


@wp.func
def swap_exchange_chunk(b: BuildData, t: BuildTask, chunk: int):
    """Swap, step 2: the r-th right-marked triangle left of the pivot trades places with the
    r-th entry of the separate index array."""
    ones = b.scan[t.start + chunk]
    first = chunk * CHUNK
    last = wp.min(first + CHUNK, t.pivot)
    for k in range(first, last):
        if b.mark[t.start + k] != wp.int8(0):
            i = t.start + k
            r = t.start + ones
            j = b.swap_pos[r]
            b.perm[j] = b.perm[i]
            b.tri_lo[j] = b.tri_lo[i]
            b.tri_hi[j] = b.tri_hi[i]
            b.perm[i] = b.swap_id[r]
            b.tri_lo[i] = b.swap_lo[r]
            b.tri_hi[i] = b.swap_hi[r]
            ones += 1


# ---------------------------------------------------------------- AABB


@wp.func
def aabb_chunk(b: BuildData, t: BuildTask, level: int, chunk: int):
    """Reduction of boxes over the two halves [0, pivot) and [pivot, count) separately; chunks
    of the left half come first."""
    n_left_chunks = segment_chunks(t.pivot, level)
    base = t.start
    n = t.pivot
    c = chunk
    if chunk >= n_left_chunks:
        base = t.start + t.pivot
        n = t.count - t.pivot
        c = chunk - n_left_chunks
    lo = wp.vec3(INF)
    hi = wp.vec3(-INF)
    clo = wp.vec3(INF)
    chi = wp.vec3(-INF)
    if level == 1:
        first = base + c * CHUNK
        last = wp.min(first + CHUNK, base + n)
        for i in range(first, last):
            lo = min3(lo, b.tri_lo[i])
            hi = max3(hi, b.tri_hi[i])
            clo = min3(clo, centroid(b, i))
            chi = max3(chi, centroid(b, i))
    else:
        src = level_base(base, n, level - 1)
        first = src + c * CHUNK
        last = wp.min(first + CHUNK, src + level_size(n, level - 1))
        for i in range(first, last):
            lo = min3(lo, b.box_lo[i])
            hi = max3(hi, b.box_hi[i])
            clo = min3(clo, b.cbox_lo[i])
            chi = max3(chi, b.cbox_hi[i])
    dst = level_base(base, n, level) + c
    b.box_lo[dst] = lo
    b.box_hi[dst] = hi
    b.cbox_lo[dst] = clo
    b.cbox_hi[dst] = chi


@wp.func
def segment_chunks(n: int, level: int) -> int:
    """AABB chunks of one half at `level`: none once that half is reduced to one box (its
    range has room for its own levels only)."""
    if level > level_count(n):
        return 0
    return level_size(n, level)


@wp.func
def aabb_levels(t: BuildTask) -> int:
    return wp.max(level_count(t.pivot), level_count(t.count - t.pivot))


@wp.func
def aabb_result(b: BuildData, t: BuildTask) -> BuildTask:
    left = level_base(t.start, t.pivot, level_count(t.pivot))
    n_right = t.count - t.pivot
    right = level_base(t.start + t.pivot, n_right, level_count(n_right))
    t.llo = b.box_lo[left]
    t.lhi = b.box_hi[left]
    t.lclo = b.cbox_lo[left]
    t.lchi = b.cbox_hi[left]
    t.rlo = b.box_lo[right]
    t.rhi = b.box_hi[right]
    t.rclo = b.cbox_lo[right]
    t.rchi = b.cbox_hi[right]
    return t


# ---------------------------------------------------------------- steps and tasks


@wp.func
def pps_levels(t: BuildTask) -> int:
    return level_count(t.count)


@wp.func
def step_chunks(t: BuildTask) -> int:
    """Work chunks of the task's current step."""
    if t.phase == PHASE_SPLIT_PLANE:
        return ceil_div(t.count, CHUNK)
    if t.phase == PHASE_PPS:
        levels = pps_levels(t)
        if t.step < levels:  # up-sweep to level step + 1
            return level_size(t.count, t.step + 1)
        level = 2 * levels - 1 - t.step  # down-sweep of level `level`
        return level_size(t.count, level + 1)
    if t.phase == PHASE_SWAP:
        if t.step == 0:
            return ceil_div(t.count, CHUNK) - t.pivot / CHUNK
        return ceil_div(t.pivot, CHUNK)
    if t.phase == PHASE_AABB:
        level = t.step + 1
        return segment_chunks(t.pivot, level) + segment_chunks(t.count - t.pivot, level)
    return 0


@wp.func
def run_chunk(b: BuildData, t: BuildTask, slot: int, chunk: int):
    if t.phase == PHASE_SPLIT_PLANE:
        split_plane_chunk(b, t, slot, chunk)
    elif t.phase == PHASE_PPS:
        levels = pps_levels(t)
        if t.step < levels:
            pps_up_chunk(b, t, t.step + 1, chunk)
        else:
            pps_down_chunk(b, t, 2 * levels - 1 - t.step, chunk)
    elif t.phase == PHASE_SWAP:
        if t.step == 0:
            swap_gather_chunk(b, t, chunk)
        else:
            swap_exchange_chunk(b, t, chunk)
    elif t.phase == PHASE_AABB:
        aabb_chunk(b, t, t.step + 1, chunk)


@wp.func
def enter(t: BuildTask, phase: int) -> BuildTask:
    t.phase = phase
    t.step = 0
    t.chunks = step_chunks(t)
    return t


@wp.func
def halve(t: BuildTask) -> BuildTask:
    """No plane separates the centroids: split the range in two and compute the boxes."""
    t.pivot = t.count / 2
    return enter(t, PHASE_AABB)


@wp.func
def complete_step(b: BuildData, t: BuildTask, slot: int) -> BuildTask:
    """The last finisher interprets the step's results and moves the task on."""
    if t.phase == PHASE_SPLIT_PLANE:
        t = choose_sah_split(b, t, slot)
        if t.pivot < 0:
            return halve(t)
        return enter(t, PHASE_PPS)
    if t.phase == PHASE_PPS:
        levels = pps_levels(t)
        if t.step == levels - 1:  # the top holds the number of right triangles
            top = level_base(t.start, t.count, levels)
            t.pivot = t.count - b.scan[top]
            if t.pivot == 0 or t.pivot == t.count:
                return halve(t)
            b.scan[top] = 0
        if t.step == 2 * levels - 2:  # level 1 now holds each chunk's exclusive offset
            t.ones_left = ones_before(b, t, t.pivot)
            return enter(t, PHASE_SWAP)
    elif t.phase == PHASE_SWAP:
        if t.step == 1:
            if b.method == METHOD_SAH:
                t.phase = PHASE_DONE
                return t
            return enter(t, PHASE_AABB)
    elif t.phase == PHASE_AABB and t.step == aabb_levels(t) - 1:
        t = aabb_result(b, t)
        t.phase = PHASE_DONE
        return t
    t.step += 1
    t.chunks = step_chunks(t)
    return t


@wp.func
def new_task(
    b: BuildData, node: int, start: int, count: int, depth: int,
    lo: wp.vec3, hi: wp.vec3, clo: wp.vec3, chi: wp.vec3,
) -> BuildTask:
    """A task ready for its first step; the median plane is chosen here (sec. 4.1)."""
    t = BuildTask()
    t.node = node
    t.start = start
    t.count = count
    t.depth = depth
    t.lo = lo
    t.hi = hi
    t.clo = clo
    t.chi = chi
    t.pivot = 0
    t.ones_left = 0
    t.axis = longest_axis(clo, chi)
    if b.method == METHOD_SAH:
        if chi[t.axis] <= clo[t.axis]:
            return halve(t)  # coincident centroids: no plane separates them
        return enter(t, PHASE_SPLIT_PLANE)
    t.split = 0.5 * (clo[t.axis] + chi[t.axis])
    if not (t.split >= clo[t.axis] and t.split < chi[t.axis]):
        return halve(t)  # coincident centroids, or a midpoint that rounds onto the upper end
    return enter(t, PHASE_PPS)


@wp.func
def is_leaf(b: BuildData, count: int, depth: int) -> bool:
    return count <= b.leaf_size or depth >= b.max_depth - 1


@wp.func
def in_worker(b: BuildData, count: int, depth: int) -> bool:
    """Nodes that are not pool tasks: leaves, and small SAH ranges (see small_subtree)."""
    return is_leaf(b, count, depth) or (b.method == METHOD_SAH and count <= SMALL_TASK)


@wp.func
def split_node(b: BuildData, pool: Pool, t: BuildTask, slot: int) -> int:
    """Turn a finished task into an inner node with two children (sec. 4.2): child tasks
    reuse this slot and, for a second one, take the lowest free slot. The worker continues
    with the child in the higher of the two slots and stores the other: on one worker the
    pool then behaves as a stack (depth first), so it never holds more than depth + 1 tasks.
    Returns the slot to continue with, or -1."""
    left = shared_add(b.counters, NODE_COUNT, 2)
    write_node(b, t.node, t.lo, t.hi, left, 0)
    depth = t.depth + 1
    n_right = t.count - t.pivot
    write_node(b, left, t.llo, t.lhi, t.start, t.pivot)
    write_node(b, left + 1, t.rlo, t.rhi, t.start + t.pivot, n_right)
    left_here = in_worker(b, t.pivot, depth)
    right_here = in_worker(b, n_right, depth)
    if left_here or right_here:
        shared_max(b.counters, MAX_DEPTH, depth)
    if left_here:
        small_subtree(b, left, depth)
    if right_here:
        small_subtree(b, left + 1, depth)
    if left_here and right_here:
        pool_release(pool, slot)
        return -1
    if left_here:
        b.tasks[slot] = new_task(b, left + 1, t.start + t.pivot, n_right, depth, t.rlo, t.rhi,
                                 t.rclo, t.rchi)
        return slot
    lt = new_task(b, left, t.start, t.pivot, depth, t.llo, t.lhi, t.lclo, t.lchi)
    if right_here:
        b.tasks[slot] = lt
        return slot
    rt = new_task(b, left + 1, t.start + t.pivot, n_right, depth, t.rlo, t.rhi, t.rclo, t.rchi)
    other = pool_alloc(pool)
    if other < 0:
        return -1
    keep = wp.max(slot, other)
    store = wp.min(slot, other)
    b.tasks[keep] = lt
    b.tasks[store] = rt
    pool_publish(pool, store, rt.chunks)
    return keep


@wp.func
def add_cycles(b: BuildData, worker: int, phase: int, since: wp.int64):
    i = worker * CYCLE_ROW + phase
    b.phase_cycles[i] = b.phase_cycles[i] + (cycles() - since)


@wp.func
def advance(b: BuildData, pool: Pool, worker: int, slot: int, t: BuildTask):
    """Run steps inline while they have fewer than K chunks (sec. 3.4), finishing tasks and
    continuing with a child; publish the first step that is big enough for the pool."""
    s = slot
    task = t
    while True:
        phase = task.phase
        since = cycles()
        task = complete_step(b, task, s)
        add_cycles(b, worker, phase, since)
        if task.phase == PHASE_DONE:
            since = cycles()
            next_slot = split_node(b, pool, task, s)
            add_cycles(b, worker, PHASE_DONE, since)
            if next_slot < 0:
                return
            s = next_slot
            task = b.tasks[s]
        if task.chunks >= pool.min_chunks:
            b.tasks[s] = task
            pool_hand_over(pool, s, task.chunks)
            return
        since = cycles()
        for c in range(task.chunks):
            run_chunk(b, task, s, c)
        add_cycles(b, worker, task.phase, since)


@wp.func
def run_chunks(b: BuildData, pool: Pool, worker: int, slot: int, t: BuildTask, first: int,
               count: int):
    """Acquired chunks of a pool step. A SplitPlane step shared with other workers is
    binned into this worker's own bins first and merged once (sec. 4.1)."""
    since = cycles()
    if t.phase == PHASE_SPLIT_PLANE and count < t.chunks:
        own = pool.capacity + worker
        for c in range(first, first + count):
            split_plane_chunk(b, t, own, c)
        merge_bins(b, own, slot)
    else:
        for c in range(first, first + count):
            run_chunk(b, t, slot, c)
    add_cycles(b, worker, t.phase, since)


@wp.kernel
def build_worker(b: BuildData, pool: Pool, first_worker: int):
    """The persistent worker of Algorithm 1."""
    worker = first_worker + wp.tid()
    idle_since = wp.int64(-1)
    while pool_running(pool):
        got = pool_acquire(pool)
        slot = got[0]
        if slot < 0:
            idle_since = pool_idle(pool, idle_since)
            continue
        idle_since = wp.int64(-1)
        run_chunks(b, pool, worker, slot, b.tasks[slot], got[1], got[2])
        if pool_finish(pool, slot, got[2]):
            advance(b, pool, worker, slot, b.tasks[slot])


@wp.kernel
def start_build(b: BuildData, pool: Pool, root_lo: wp.vec3, root_hi: wp.vec3,
                root_clo: wp.vec3, root_chi: wp.vec3, count: int):
    """Store the root task (Algorithm 1: 'in serial, insert the first task')."""
    b.counters[NODE_COUNT] = 1
    if in_worker(b, count, 0):
        write_node(b, 0, root_lo, root_hi, 0, count)
        small_subtree(b, 0, 0)
        return
    slot = pool_alloc(pool)
    t = new_task(b, 0, 0, count, 0, root_lo, root_hi, root_clo, root_chi)
    b.tasks[slot] = t
    pool_publish(pool, slot, t.chunks)


@wp.kernel
def reset_bins(b: BuildData):
    reset_bin(b, wp.tid())


@wp.func
def is_degenerate(a: wp.vec3, b: wp.vec3, c: wp.vec3) -> bool:
    """Zero area: the float64 cross product of the float32 edges is exactly zero."""
    a64 = wp.vec3d(wp.float64(a[0]), wp.float64(a[1]), wp.float64(a[2]))
    e1 = wp.vec3d(wp.float64(b[0]), wp.float64(b[1]), wp.float64(b[2])) - a64
    e2 = wp.vec3d(wp.float64(c[0]), wp.float64(c[1]), wp.float64(c[2])) - a64
    n = wp.cross(e1, e2)
    zero = wp.float64(0.0)
    return n[0] == zero and n[1] == zero and n[2] == zero


@wp.kernel
def degenerate_flags(vertices: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.vec3i),
                     out: wp.array(dtype=wp.int8)):
    f = indices[wp.tid()]
    out[wp.tid()] = wp.int8(wp.where(is_degenerate(vertices[f[0]], vertices[f[1]],
                                                   vertices[f[2]]), 1, 0))


@wp.kernel
def triangle_boxes(
    vertices: wp.array(dtype=wp.vec3),
    indices: wp.array(dtype=wp.vec3i),
    tri_lo: wp.array(dtype=wp.vec3),
    tri_hi: wp.array(dtype=wp.vec3),
    valid: wp.array(dtype=int),
    bounds: wp.array(dtype=wp.vec3),
):
    """Per-triangle boxes; `valid` is 0 for zero-area triangles (an exact
    float64 cross product of the float32 edges), which the build leaves out. bounds[0..3]
    get the scene's box and centroid box over the valid ones."""
    i = wp.tid()
    f = indices[i]
    a = vertices[f[0]]
    bb = vertices[f[1]]
    c = vertices[f[2]]
    lo = min3(min3(a, bb), c)
    hi = max3(max3(a, bb), c)
    mid = 0.5 * (lo + hi)
    tri_lo[i] = lo
    tri_hi[i] = hi
    valid[i] = 0
    if not is_degenerate(a, bb, c):
        valid[i] = 1
        wp.atomic_min(bounds, 0, lo)
        wp.atomic_max(bounds, 1, hi)
        wp.atomic_min(bounds, 2, mid)
        wp.atomic_max(bounds, 3, mid)


@wp.kernel
def compact_valid(
    valid: wp.array(dtype=int),
    offsets: wp.array(dtype=int),
    lo: wp.array(dtype=wp.vec3),
    hi: wp.array(dtype=wp.vec3),
    b: BuildData,
):
    """The initial index array: the valid triangles in order, with their boxes."""
    i = wp.tid()
    if valid[i] != 0:
        k = offsets[i]
        b.perm[k] = i
        b.tri_lo[k] = lo[i]
        b.tri_hi[k] = hi[i]


@wp.kernel
def gather_leaf_triangles(
    vertices: wp.array(dtype=wp.vec3),
    indices: wp.array(dtype=wp.vec3i),
    perm: wp.array(dtype=int),
    tri_verts: wp.array(dtype=wp.vec3),
):
    """Triangles in leaf order, three vertices each, so a leaf reads one contiguous block."""
    i = wp.tid()
    f = indices[perm[i]]
    tri_verts[3 * i] = vertices[f[0]]
    tri_verts[3 * i + 1] = vertices[f[1]]
    tri_verts[3 * i + 2] = vertices[f[2]]
