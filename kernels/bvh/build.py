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

The worker loop is the pool's (`pool.worker`); PPS, Swap and AABB are the pool's chunk
phases (`pool.phases`) over the task's index range, with level 1 of PPS (the marks) and of
AABB (the boxes of the items) here.
"""

from __future__ import annotations

import warp as wp

from ..core.atomics import shared_add, shared_max
from ..core.box import INF, max3, median_plane, min3
from ..core.claim import Claims, claimed_items
from ..core.compile_options import MODULE_OPTIONS
from ..core.mesh import triangle_corners
from ..core.triangle import is_degenerate
from ..pool import clock
from ..pool.chunks import CHUNK, ceil_div, level_count
from ..pool.phases import (
    aabb_chunks,
    ones_before,
    pps_chunks,
    pps_count,
    pps_down_chunk,
    pps_total,
    pps_up_chunk,
    reduce_boxes,
    reduced_box,
    store_box,
    swap_chunks,
    swap_exchange_chunk,
    swap_gather_chunk,
)
from ..pool.state import Pool, pool_alloc, pool_publish, pool_release
from ..pool.worker import Application, make_worker
from .binned_sah import (
    bin_of,
    bin_scale,
    choose_sah_split,
    merge_bins,
    reset_bin,
    split_plane_chunks,
)
from .build_data import (
    BINS,
    MAX_DEPTH,
    METHOD_SAH,
    NODE_COUNT,
    PHASE_AABB,
    PHASE_DONE,
    PHASE_PPS,
    PHASE_SPLIT_PLANE,
    PHASE_SWAP,
    SMALL_TASK,
    SWAP_IN_PLACE,
    BuildData,
    BuildItem,
    BuildTask,
    centroid,
    write_node,
)
from .sweep_sah import small_subtree

wp.set_module_options(MODULE_OPTIONS)


@wp.func
def goes_right(b: BuildData, t: BuildTask, scale: float, i: int) -> bool:
    """Marked 1 in PPS: right of the SAH plane (`scale` from bin_scale) or the median."""
    it = b.items[i]
    c = 0.5 * (it.lo[t.axis] + it.hi[t.axis])
    if b.method == METHOD_SAH:
        return bin_of(c, t.clo[t.axis], scale) > t.split_bin
    return c > t.split


@wp.func
def mark_chunk(b: BuildData, t: BuildTask, chunk: int):
    """PPS, level 1: mark a chunk's triangles right of the plane (1) or not, and count them."""
    first = t.start + chunk * CHUNK
    scale = float(0.0)
    if b.method == METHOD_SAH:
        scale = bin_scale(t)
    total = int(0)
    for i in range(first, wp.min(first + CHUNK, t.start + t.count)):
        right = int(0)
        if goes_right(b, t, scale, i):
            right = 1
        b.mark[i] = wp.int8(right)
        total += right
    pps_count(b.scan, t.start, chunk, total)


# exchange_in_place on a CPU, as native code: which side an item goes to is found for a
# block of items at a time without a branch (their positions written, a counter moved by
# the answer; BlockQuicksort's idea, Edelkamp and Weiss 2016), then the blocks' pairs
# swapped, in the same order: the r-th right of the plane in front of the pivot with the
# r-th left of it behind. The branch on each item's side was mispredicted about as often
# as the sides alternate. (CUDA: 0, the loop below runs.)
EXCHANGE_SOURCE = """
#if !defined(__CUDA_ARCH__)
    auto* it = items.data;
    auto right = [&](int i) -> int {  // goes_right: the same float32 operations
        const float c = 0.5f * (it[i].lo.c[axis] + it[i].hi.c[axis]);
        int k = (int)((c - origin) * scale);
        k = k < 0 ? 0 : (k > BIN_COUNT - 1 ? BIN_COUNT - 1 : k);
        return k > split_bin;
    };
    constexpr int RUN = 64;
    int front[RUN], back[RUN];  // positions of right-goers in front, left-goers behind
    int nf = 0, hf = 0, nb = 0, hb = 0;  // how many each holds, and the next to swap
    int i = start, j = start + pivot;
    const int front_end = start + pivot, back_end = start + count;
    while (true) {
        if (hf == nf) {
            if (i >= front_end)
                break;
            hf = nf = 0;
            const int stop = i + RUN < front_end ? i + RUN : front_end;
            for (; i < stop; ++i) {
                front[nf] = i;
                nf += right(i);
            }
            continue;
        }
        if (hb == nb) {
            if (j >= back_end)
                break;  // (not reached: the pivot counts the items left of the plane)
            hb = nb = 0;
            const int stop = j + RUN < back_end ? j + RUN : back_end;
            for (; j < stop; ++j) {
                back[nb] = j;
                nb += 1 - right(j);
            }
            continue;
        }
        const int m = nf - hf < nb - hb ? nf - hf : nb - hb;
        for (int q = 0; q < m; ++q) {
            const auto swapped = it[front[hf + q]];
            it[front[hf + q]] = it[back[hb + q]];
            it[back[hb + q]] = swapped;
        }
        hf += m;
        hb += m;
    }
    return 1;
#else
    return 0;
#endif
""".replace("BIN_COUNT", str(int(BINS)))


@wp.func_native(EXCHANGE_SOURCE)
def exchange_native(items: wp.array(dtype=BuildItem), start: int, count: int, pivot: int,
                    axis: int, origin: float, scale: float, split_bin: int) -> int:
    """exchange_in_place's exchange (EXCHANGE_SOURCE); 0 where not compiled."""
    ...


@wp.func
def exchange_in_place(b: BuildData, t: BuildTask):
    """Swap by one worker without PPS: the r-th triangle right of the plane in front of the
    pivot trades places with the r-th one left of it behind the pivot, the exchange that
    PPS and Swap's two steps make (the same order, so the same tree), in one pass over the
    range and without the mark, scan and spare arrays."""
    scale = bin_scale(t)
    if exchange_native(b.items, t.start, t.count, t.pivot, t.axis, t.clo[t.axis], scale,
                       t.split_bin) != 0:
        return
    j = t.start + t.pivot
    for i in range(t.start, t.start + t.pivot):
        if goes_right(b, t, scale, i):
            while goes_right(b, t, scale, j):
                j += 1
            it = b.items[i]
            b.items[i] = b.items[j]
            b.items[j] = it
            j += 1


@wp.func
def box_chunk(b: BuildData, base: int, n: int, chunk: int):
    """AABB, level 1: the box and centroid box of a chunk of one half's triangles."""
    lo = wp.vec3(INF)
    hi = wp.vec3(-INF)
    clo = wp.vec3(INF)
    chi = wp.vec3(-INF)
    first = base + chunk * CHUNK
    for i in range(first, wp.min(first + CHUNK, base + n)):
        it = b.items[i]
        c = centroid(it)
        lo = min3(lo, it.lo)
        hi = max3(hi, it.hi)
        clo = min3(clo, c)
        chi = max3(chi, c)
    store_box(b.box_lo, b.box_hi, base, n, 1, chunk, lo, hi)
    store_box(b.cbox_lo, b.cbox_hi, base, n, 1, chunk, clo, chi)


@wp.func
def aabb_chunk(b: BuildData, t: BuildTask, level: int, chunk: int):
    """Reduction of boxes over the two halves [0, pivot) and [pivot, count) separately (two
    segments); chunks of the left half come first."""
    n_left_chunks = aabb_chunks(t.pivot, level)
    base = t.start
    n = t.pivot
    c = chunk
    if chunk >= n_left_chunks:
        base = t.start + t.pivot
        n = t.count - t.pivot
        c = chunk - n_left_chunks
    if level == 1:
        box_chunk(b, base, n, c)
    else:
        reduce_boxes(b.box_lo, b.box_hi, base, n, level, c)
        reduce_boxes(b.cbox_lo, b.cbox_hi, base, n, level, c)


@wp.func
def aabb_levels(t: BuildTask) -> int:
    return wp.max(level_count(t.pivot), level_count(t.count - t.pivot))


@wp.func
def aabb_result(b: BuildData, t: BuildTask) -> BuildTask:
    n_right = t.count - t.pivot
    box = reduced_box(b.box_lo, b.box_hi, t.start, t.pivot)
    cbox = reduced_box(b.cbox_lo, b.cbox_hi, t.start, t.pivot)
    t.llo = box[0]
    t.lhi = box[1]
    t.lclo = cbox[0]
    t.lchi = cbox[1]
    box = reduced_box(b.box_lo, b.box_hi, t.start + t.pivot, n_right)
    cbox = reduced_box(b.cbox_lo, b.cbox_hi, t.start + t.pivot, n_right)
    t.rlo = box[0]
    t.rhi = box[1]
    t.rclo = cbox[0]
    t.rchi = cbox[1]
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
        return pps_chunks(t.count, levels, levels, t.step)
    if t.phase == PHASE_SWAP:
        if t.step == SWAP_IN_PLACE:
            return 1
        return swap_chunks(t.count, t.pivot, t.step)
    if t.phase == PHASE_AABB:
        level = t.step + 1
        return aabb_chunks(t.pivot, level) + aabb_chunks(t.count - t.pivot, level)
    return 0


@wp.func
def run_chunk(b: BuildData, t: BuildTask, chunk: int):
    """A chunk of a PPS, Swap or AABB step."""
    if t.phase == PHASE_PPS:
        levels = pps_levels(t)
        if t.step == 0:
            mark_chunk(b, t, chunk)
        elif t.step < levels:
            pps_up_chunk(b.scan, t.start, t.count, t.step + 1, chunk)
        else:
            pps_down_chunk(b.scan, t.start, t.count, 2 * levels - 1 - t.step, chunk)
    elif t.phase == PHASE_SWAP:
        if t.step == SWAP_IN_PLACE:
            exchange_in_place(b, t)
        elif t.step == 0:
            swap_gather_chunk(b.items, b.spare, b.spare_pos, b.mark, b.scan, t.start, t.count,
                              t.pivot, t.ones_left, chunk)
        else:
            swap_exchange_chunk(b.items, b.spare, b.spare_pos, b.mark, b.scan, t.start,
                                t.pivot, chunk)
    elif t.phase == PHASE_AABB:
        aabb_chunk(b, t, t.step + 1, chunk)


@wp.func
def run_chunks(b: BuildData, worker: int, slot: int, t: BuildTask, first: int, count: int):
    """Chunks of a step (the worker's `run_chunks`). A SplitPlane step shared with other
    workers is binned into this worker's own bins first and merged once (sec. 4.1); one
    that this worker has alone, into the task's bins."""
    if t.phase != PHASE_SPLIT_PLANE:
        for c in range(first, first + count):
            run_chunk(b, t, c)
    elif count < t.chunks:
        own = b.worker_bins + worker
        split_plane_chunks(b, t, own, first, count)
        merge_bins(b, own, slot)
    else:
        split_plane_chunks(b, t, slot, first, count)


@wp.func
def complete_step(b: BuildData, t: BuildTask, slot: int) -> BuildTask:
    """The last finisher interprets the step's results and moves the task on (the worker's
    `complete_step`)."""
    if t.phase == PHASE_SPLIT_PLANE:
        t = choose_sah_split(b, t, slot)
        if t.pivot < 0:
            return halve(t)
        if t.count <= b.serial_max:  # the bins counted the pivot: no PPS needed
            t.phase = PHASE_SWAP
            t.step = SWAP_IN_PLACE
            t.chunks = step_chunks(t)
            return t
        return enter(t, PHASE_PPS)
    if t.phase == PHASE_PPS:
        levels = pps_levels(t)
        if t.step == levels - 1:  # the top holds the number of right triangles
            t.pivot = t.count - pps_total(b.scan, t.start, t.count)
            if t.pivot == 0 or t.pivot == t.count:
                return halve(t)
        if t.step == 2 * levels - 2:  # level 1 now holds each chunk's exclusive offset
            t.ones_left = ones_before(b.scan, b.mark, t.start, t.count, t.pivot)
            return enter(t, PHASE_SWAP)
    elif t.phase == PHASE_SWAP:
        if t.step >= 1:  # the exchange, or SWAP_IN_PLACE
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
    plane = median_plane(clo, chi)  # the longest axis of the centroid box, and its middle
    t.axis = int(plane[0])
    if b.method == METHOD_SAH:
        if chi[t.axis] <= clo[t.axis]:
            return halve(t)  # coincident centroids: no plane separates them
        return enter(t, PHASE_SPLIT_PLANE)
    t.split = plane[1]
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
def split_node(b: BuildData, pool: Pool, worker: int, t: BuildTask, slot: int) -> int:
    """Turn a finished task into an inner node with two children (sec. 4.2): child tasks
    reuse this slot and, for a second one, take the lowest free slot. The worker continues
    with the child in the higher of the two slots and stores the other: on one worker the
    pool then behaves as a stack (depth first), so it never holds more than depth + 1 tasks.
    Returns the slot to continue with, or -1."""
    left = shared_add(b.counters, NODE_COUNT, 2)
    write_node(b.nodes, t.node, t.lo, t.hi, left, 0)
    depth = t.depth + 1
    n_right = t.count - t.pivot
    write_node(b.nodes, left, t.llo, t.lhi, t.start, t.pivot)
    write_node(b.nodes, left + 1, t.rlo, t.rhi, t.start + t.pivot, n_right)
    left_here = in_worker(b, t.pivot, depth)
    right_here = in_worker(b, n_right, depth)
    if left_here or right_here:
        shared_max(b.counters, MAX_DEPTH, depth)
    if left_here:
        small_subtree(b, left, depth, worker)
    if right_here:
        small_subtree(b, left + 1, depth, worker)
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


build_worker = make_worker(Application(
    data=BuildData, task=BuildTask, run_chunks=run_chunks, complete_step=complete_step,
    finish_task=split_node, done=PHASE_DONE, module=__name__, name="build"))


@wp.kernel
def start_build(b: BuildData, pool: Pool, root_lo: wp.vec3, root_hi: wp.vec3,
                root_clo: wp.vec3, root_chi: wp.vec3, count: int):
    """Store the root task (Algorithm 1: 'in serial, insert the first task')."""
    b.counters[NODE_COUNT] = 1
    if in_worker(b, count, 0):
        write_node(b.nodes, 0, root_lo, root_hi, 0, count)
        small_subtree(b, 0, 0, 0)
        return
    slot = pool_alloc(pool)
    t = new_task(b, 0, 0, count, 0, root_lo, root_hi, root_clo, root_chi)
    b.tasks[slot] = t
    pool_publish(pool, slot, t.chunks)


@wp.kernel
def reset_bins(b: BuildData):
    reset_bin(b, wp.tid())


@wp.func
def triangle_box(vertices: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.vec3i),
                 i: int) -> wp.mat33:
    """Rows: triangle i's corners' min and max, and whether it is degenerate (x: 1.0) or
    not (0.0): zero area by an exact float64 cross product of the float32 edges."""
    t = triangle_corners(vertices, indices, i)
    flat = wp.where(is_degenerate(t[0], t[1], t[2]), 1.0, 0.0)
    return wp.matrix_from_rows(min3(min3(t[0], t[1]), t[2]), max3(max3(t[0], t[1]), t[2]),
                               wp.vec3(flat, 0.0, 0.0))


@wp.kernel
def triangle_items(
    vertices: wp.array(dtype=wp.vec3),
    indices: wp.array(dtype=wp.vec3i),
    first: int,
    part: int,
    bounds: wp.array(dtype=wp.vec3),
    flat: wp.array(dtype=int),
    items: wp.array(dtype=BuildItem),
):
    """The initial index array straight from the triangles, first + tid (one part of them,
    a host thread each on CPU): item i is triangle i with its box, or, for a zero-area
    triangle, which the build leaves out, `tri` -1 (counted in flat[part]: api.drop_left_out
    then takes them out). bounds[4 part .. 4 part + 3] get the part's box and centroid box
    over the others (a part's own: CPU atomics are plain updates, safe within one launch
    only)."""
    i = first + wp.tid()
    box = triangle_box(vertices, indices, i)
    it = BuildItem()
    it.lo = box[0]
    it.tri = i
    it.hi = box[1]
    if box[2][0] == 0.0:
        mid = 0.5 * (box[0] + box[1])
        wp.atomic_min(bounds, 4 * part, box[0])
        wp.atomic_max(bounds, 4 * part + 1, box[1])
        wp.atomic_min(bounds, 4 * part + 2, mid)
        wp.atomic_max(bounds, 4 * part + 3, mid)
    else:
        it.tri = -1
        wp.atomic_add(flat, part, 1)
    items[i] = it


@wp.kernel
def kept_items(items: wp.array(dtype=BuildItem), kept: wp.array(dtype=int)):
    i = wp.tid()
    kept[i] = wp.where(items[i].tri >= 0, 1, 0)


@wp.kernel
def compact_items(items: wp.array(dtype=BuildItem), kept: wp.array(dtype=int),
                  offsets: wp.array(dtype=int), out: wp.array(dtype=BuildItem)):
    """The kept items, in order, at their `offsets` (an exclusive scan of `kept`)."""
    i = wp.tid()
    if kept[i] != 0:
        out[offsets[i]] = items[i]


@wp.kernel
def gather_leaf_ids(items: wp.array(dtype=BuildItem), first: int,
                    tri_ids: wp.array(dtype=int)):
    """The caller's index of each triangle in leaf order (first + tid: one part of them)."""
    i = first + wp.tid()
    tri_ids[i] = items[i].tri


@wp.kernel
def leaf_triangles(vertices: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.vec3i),
                   tri_ids: wp.array(dtype=int), tri_verts: wp.array(dtype=wp.vec3),
                   claims: Claims):
    """The binary traversal's leaves: leaf position i's three vertices one after the other
    (triangle tri_ids[i] of the mesh), so a leaf reads one contiguous run. After a build
    and after a refit."""
    items = claimed_items(claims, wp.tid())
    for i in range(items[0], items[1]):
        t = triangle_corners(vertices, indices, tri_ids[i])
        tri_verts[3 * i] = t[0]
        tri_verts[3 * i + 1] = t[1]
        tri_verts[3 * i + 2] = t[2]


# this module's kernels and the pool clock's rate probe (see core.launch.load_modules)
WARP_MODULES = (build_worker.module, *clock.WARP_MODULES)
