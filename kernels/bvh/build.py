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

from ..core.box import INF, longest_axis, max3, min3
from ..core.triangle import is_degenerate
from ..pool.atomics import cycles, shared_add, shared_max
from ..pool.chunks import CHUNK, ceil_div, level_base, level_count, level_size
from ..pool.state import (
    Pool,
    pool_acquire,
    pool_alloc,
    pool_finish,
    pool_hand_over,
    pool_idle,
    pool_publish,
    pool_release,
    pool_running,
)
from .binned_sah import (
    bin_of,
    bin_scale,
    choose_sah_split,
    merge_bins,
    reset_bin,
    split_plane_chunk,
)
from .build_data import (
    CYCLE_ROW,
    MAX_DEPTH,
    METHOD_SAH,
    NODE_COUNT,
    PHASE_AABB,
    PHASE_DONE,
    PHASE_PPS,
    PHASE_SPLIT_PLANE,
    PHASE_SWAP,
    SMALL_TASK,
    BuildData,
    BuildTask,
    centroid,
    write_node,
)
from .sweep_sah import small_subtree

wp.set_module_options({"enable_backward": False, "optimization_level": 3})


@wp.func
def goes_right(b: BuildData, t: BuildTask, scale: float, i: int) -> bool:
    """Marked 1 in PPS: right of the SAH plane (`scale` from bin_scale) or the median."""
    c = 0.5 * (b.tri_lo[i][t.axis] + b.tri_hi[i][t.axis])
    if b.method == METHOD_SAH:
        return bin_of(c, t.clo[t.axis], scale) > t.split_bin
    return c > t.split


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
