"""Task-pool divide-and-conquer ray tracing (2012 paper, sec. 5).

No acceleration structure: a task holds a node box, an interval of the ray index array and
one of the triangle index array. Two task kinds share the pool of `kernels.pool`:
  intersection   one step; each work chunk covers CHUNK ray-triangle pairs; the closest hit
                 per ray is an atomic min on a packed (t, triangle) key (deterministic)
  subdivision    SplitPlane (spatial median or RDH), PPS1, Swap1, PPS2, Swap2, AABB, then
                 seven children chosen from the dependency table (`table.py`)
Rays are classified left / straddling / right / clipped against the plane within the node
box; triangles left / straddling / right by their boxes. A ray whose closest hit so far lies
before its entry into the node box is clipped too (ordered early termination). Boxes and
ray spans are widened by `margin`, so no hit that the watertight test reports is lost to
rounding.

PPS, Swap and AABB are the pool's chunk phases (`pool.phases`), here on up to three
segments at once (PPS2: the left and right ray parts and the left triangle part); a step's
chunks are the segments' chunks one after another. Level 1 of PPS (classifying and marking
rays and triangles) and of AABB (the triangles' boxes) is this module's. The worker is the
pool's (`pool.worker.make_worker`); this module supplies `run_chunks`, `complete_step` and
`finish_task` (store the children, or release an intersection task and activate its
dependants).
"""

from __future__ import annotations

import time

import numpy as np
import warp as wp

from ..core import mesh as core_mesh
from ..core.atomics import shared_add, shared_max
from ..core.box import INF, max3, median_plane, min3
from ..core.compile_options import MODULE_OPTIONS
from ..core.device_arrays import DeviceArrays
from ..core.hits import Hits
from ..core.mesh import DeviceMesh
from ..core.ray import make_ray
from ..core.triangle import intersect_triangle
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
from ..pool.state import (
    Pool,
    check_pool,
    default_workers,
    make_pool,
    pool_alloc,
    pool_publish,
    pool_release,
    pool_resolve,
    pool_wait,
)
from ..pool.worker import CYCLE_ROW, Application, launch_workers, make_worker
from . import records, table
from .classify import (
    CLS_CLIPPED,
    CLS_LEFT,
    CLS_RIGHT,
    CLS_STRADDLE,
    ray_side,
    ray_span,
    side_of,
    widen,
    widened_range,
)
from .options import DacrtOptions
from .rdh import choose_rdh_split, rdh_children, sample_counts, split_plane_chunk
from .records import (
    KEY_NONE,
    RayRecord,
    hit_key,
    key_t,
    rays_and_triangles,
    scene_box,
    shared_min_u64,
    unpack_hits,
)
from .stats import DacrtStats
from .task import (
    C_KPAIRS,
    C_LEAVES,
    C_MAX_DEPTH,
    C_OVERFLOW,
    C_RAYS_SORTED,
    C_SKIPPED,
    C_TASKS,
    C_TRIS_SORTED,
    C_VISITS,
    CAND_BOXES,
    CAND_INTS,
    COUNTERS,
    MAX_SUCC,
    PH_AABB,
    PH_DONE,
    PH_INTERSECT,
    PH_PPS1,
    PH_PPS2,
    PH_SORT,
    PH_SPLIT_PLANE,
    PH_SWAP1,
    PH_SWAP2,
    PHASE_NAMES,
    RAY_INTERVAL,
    ROLE_BOX,
    ROLE_RAYS,
    ROLE_RAYS_LEFT,
    ROLE_RAYS_RIGHT,
    ROLE_TRIS,
    ROLE_TRIS_LEFT,
    SPLIT_MEDIAN,
    SPLIT_RDH,
    T_COUNT,
    T_IS_SINK,
    T_ORDER,
    T_PREDS,
    T_SINKS,
    T_SUCC,
    TABLE,
    TRI_INTERVAL,
    DacrtData,
    DacrtTask,
    Segment3,
    Slots7,
)

wp.set_module_options(MODULE_OPTIONS)

PREFETCH = wp.constant(16)  # items ahead that the sort's classification loops prefetch
SPLITS: dict[str, int] = {"median": int(SPLIT_MEDIAN), "rdh": int(SPLIT_RDH)}
SMALL_ITEMS_CPU = 32768  # least small_items on CPU (measured: 4096 -> 32768 saved 3-7%)
# workers per multiprocessor on CUDA: on an H200, Sponza 512^2 with the papers' constants took
# 1.6 s with 8, 1.3 s with 32, 2.0 s with 128 and 3.1 s with 256 per SM (the build's count)
WORKERS_PER_SM = 32


@wp.func_native(
    """
#if !defined(__CUDA_ARCH__)
__builtin_prefetch(&rays.data[i]);
__builtin_prefetch(&best.data[i]);
#endif
"""
)
def prefetch_ray(rays: wp.array(dtype=RayRecord), best: wp.array(dtype=wp.uint64), i: int):
    """Ask the CPU's caches for what classify_ray reads of ray i, a few rays ahead of the
    loop (the gather by ray id misses the caches in big tasks); nothing on CUDA."""
    ...


@wp.func_native(
    """
#if !defined(__CUDA_ARCH__)
__builtin_prefetch(&lo.data[i]);
__builtin_prefetch(&hi.data[i]);
#endif
"""
)
def prefetch_tri(lo: wp.array(dtype=wp.vec3), hi: wp.array(dtype=wp.vec3), i: int):
    """prefetch_ray for a triangle's box."""
    ...


@wp.func
def classify_ray(d: DacrtData, t: DacrtTask, ray: int, r: RayRecord) -> int:
    """Left / straddling / right of the plane within the node box, or clipped: misses the
    box, or already hit something before entering it (sec. 5.2, PPS1)."""
    w = widened_range(r)
    span = ray_span(r, t.lo, t.hi, w[0], w[1])
    if span[0] == INF or key_t(d.io.best[ray]) < span[0]:
        return CLS_CLIPPED
    return ray_side(r, span, t.axis, t.split, d.io.margin)


@wp.func
def classify_tri(d: DacrtData, t: DacrtTask, tri: int) -> int:
    return side_of(wp.vec2(d.io.tri_lo[tri][t.axis], d.io.tri_hi[tri][t.axis]), t.split, 0.0)


# ---------------------------------------------------------------- segment storage


@wp.func
def mark_item(d: DacrtData, t: DacrtTask, role: int, i: int) -> int:
    """Classify (PPS1) or look up (PPS2) the item at position i: bit 0 set if it goes
    behind the pivot, bit 1 for a straddling ray heading to -axis (PPS1)."""
    if role == ROLE_RAYS:
        ray = d.ray_ids[i]
        r = d.io.rays[ray]
        c = classify_ray(d, t, ray, r)
        d.ray_cls[ray] = wp.int8(c)
        m = int(c >= CLS_RIGHT)
        d.ray_mark[i] = wp.int8(m)
        if c == CLS_STRADDLE and r.inv_dir[t.axis] < 0.0:
            return m + 2
        return m
    if role == ROLE_TRIS:
        tri = d.tri_ids[i]
        c = classify_tri(d, t, tri)
        d.tri_cls[tri] = wp.int8(c)
        m = int(c >= CLS_RIGHT)
        d.tri_mark[i] = wp.int8(m)
        return m
    if role == ROLE_TRIS_LEFT:
        m = int(int(d.tri_cls[d.tri_ids[i]]) >= CLS_STRADDLE)
        d.tri_mark[i] = wp.int8(m)
        return m
    c = int(d.ray_cls[d.ray_ids[i]])
    m = int(c >= CLS_STRADDLE)
    if role == ROLE_RAYS_RIGHT:
        m = int(c >= CLS_CLIPPED)
    d.ray_mark[i] = wp.int8(m)
    return m


@wp.func
def add_segment(s: Segment3, is_tri: int, start: int, size: int, role: int) -> Segment3:
    if size > 0:
        k = s.count
        s.is_tri[k] = is_tri
        s.start[k] = start
        s.size[k] = size
        s.role[k] = role
        s.count = k + 1
    return s


@wp.func
def segment_levels(t: DacrtTask) -> int:
    levels = int(0)
    for k in range(t.seg.count):
        levels = wp.max(levels, level_count(t.seg.size[k]))
    return levels


# ---------------------------------------------------------------- PPS1 / PPS2 / Swap / AABB


@wp.func
def mark_chunk(d: DacrtData, t: DacrtTask, slot: int, k: int, chunk: int):
    """PPS level 1 of segment k (sec. 5.2, PPS1 and PPS2: the 32-ary PPS of sec. 4.1): mark
    and count a chunk's items by the segment's role; straddling rays heading to -axis are
    counted per slot (they decide which side is near)."""
    base = t.seg.start[k]
    first = base + chunk * CHUNK
    total = int(0)
    neg = int(0)
    for i in range(first, wp.min(first + CHUNK, base + t.seg.size[k])):
        code = mark_item(d, t, t.seg.role[k], i)
        total += code & 1
        neg += code >> 1
    if neg > 0:  # one atomic per chunk, not per ray
        shared_add(d.neg, slot, neg)
    if t.seg.is_tri[k] != 0:
        pps_count(d.tri_scan, base, chunk, total)
    else:
        pps_count(d.ray_scan, base, chunk, total)


@wp.func
def pps_chunk(d: DacrtData, t: DacrtTask, slot: int, k: int, chunk: int):
    """One PPS chunk of segment k: level 1 marks, then the pool's up-sweep and down-sweep on
    the segment's scan array."""
    base = t.seg.start[k]
    n = t.seg.size[k]
    levels = level_count(n)
    if t.step == 0:
        mark_chunk(d, t, slot, k, chunk)
    elif t.step < levels:
        if t.seg.is_tri[k] != 0:
            pps_up_chunk(d.tri_scan, base, n, t.step + 1, chunk)
        else:
            pps_up_chunk(d.ray_scan, base, n, t.step + 1, chunk)
    else:
        level = 2 * segment_levels(t) - 1 - t.step
        if t.seg.is_tri[k] != 0:
            pps_down_chunk(d.tri_scan, base, n, level, chunk)
        else:
            pps_down_chunk(d.ray_scan, base, n, level, chunk)


@wp.func
def pps_top(d: DacrtData, t: DacrtTask) -> DacrtTask:
    """After the up-sweep: each segment's pivot (its unmarked items)."""
    for k in range(t.seg.count):
        n = t.seg.size[k]
        if t.seg.is_tri[k] != 0:
            t.seg.pivot[k] = n - pps_total(d.tri_scan, t.seg.start[k], n)
        else:
            t.seg.pivot[k] = n - pps_total(d.ray_scan, t.seg.start[k], n)
    return t


@wp.func
def pps_end(d: DacrtData, t: DacrtTask) -> DacrtTask:
    """After the down-sweep: each segment's marked items in front of its pivot."""
    for k in range(t.seg.count):
        base = t.seg.start[k]
        n = t.seg.size[k]
        if t.seg.is_tri[k] != 0:
            t.seg.ones_left[k] = ones_before(d.tri_scan, d.tri_mark, base, n, t.seg.pivot[k])
        else:
            t.seg.ones_left[k] = ones_before(d.ray_scan, d.ray_mark, base, n, t.seg.pivot[k])
    return t


@wp.func
def swap_chunk(d: DacrtData, t: DacrtTask, k: int, chunk: int):
    """One Swap chunk of segment k (the pool's Swap, on the ray or triangle ids)."""
    base = t.seg.start[k]
    n = t.seg.size[k]
    pivot = t.seg.pivot[k]
    if t.seg.is_tri[k] != 0:
        if t.step == 0:
            swap_gather_chunk(d.tri_ids, d.tri_swap_id, d.tri_swap_pos, d.tri_mark, d.tri_scan,
                              base, n, pivot, t.seg.ones_left[k], chunk)
        else:
            swap_exchange_chunk(d.tri_ids, d.tri_swap_id, d.tri_swap_pos, d.tri_mark,
                                d.tri_scan, base, pivot, chunk)
    elif t.step == 0:
        swap_gather_chunk(d.ray_ids, d.ray_swap_id, d.ray_swap_pos, d.ray_mark, d.ray_scan,
                          base, n, pivot, t.seg.ones_left[k], chunk)
    else:
        swap_exchange_chunk(d.ray_ids, d.ray_swap_id, d.ray_swap_pos, d.ray_mark, d.ray_scan,
                            base, pivot, chunk)


@wp.func
def aabb_chunk(d: DacrtData, t: DacrtTask, k: int, chunk: int):
    """Box reduction of triangle interval k, one level per step (sec. 5.2, AABB): level 1
    from the triangles' boxes, above it the pool's reduction."""
    base = t.seg.start[k]
    n = t.seg.size[k]
    if t.step > 0:
        reduce_boxes(d.box_lo, d.box_hi, base, n, t.step + 1, chunk)
        return
    lo = wp.vec3(INF)
    hi = wp.vec3(-INF)
    first = base + chunk * CHUNK
    for i in range(first, wp.min(first + CHUNK, base + n)):
        tri = d.tri_ids[i]
        lo = min3(lo, d.io.tri_lo[tri])
        hi = max3(hi, d.io.tri_hi[tri])
    store_box(d.box_lo, d.box_hi, base, n, 1, chunk, lo, hi)


@wp.func
def segment_chunks(t: DacrtTask, k: int, top: int) -> int:
    """Chunks of segment k at the task's step (`top`: segment_levels(t))."""
    n = t.seg.size[k]
    if t.phase == PH_PPS1 or t.phase == PH_PPS2:
        return pps_chunks(n, level_count(n), top, t.step)
    if t.phase == PH_SWAP1 or t.phase == PH_SWAP2:
        return swap_chunks(n, t.seg.pivot[k], t.step)
    return aabb_chunks(n, t.step + 1)


# ---------------------------------------------------------------- steps and tasks


@wp.func
def step_chunks(d: DacrtData, t: DacrtTask) -> int:
    """Work chunks of the task's current step."""
    if t.phase == PH_INTERSECT:
        return ceil_div(t.ray_count * t.tri_count, CHUNK)
    if t.phase == PH_SPLIT_PLANE:
        return ceil_div(sample_counts(t)[t.step], CHUNK)
    if t.phase == PH_SORT:
        return 1
    total = int(0)
    top = segment_levels(t)
    for k in range(t.seg.count):
        total += segment_chunks(t, k, top)
    return total


@wp.func
def intersect_chunks(d: DacrtData, t: DacrtTask, first: int, count: int):
    """Chunks of CHUNK ray-triangle pairs, ray-major; one atomic min per ray (sec. 5.2).
    Consecutive chunks taken together set each ray up once."""
    p = first * CHUNK
    last = wp.min((first + count) * CHUNK, t.ray_count * t.tri_count)
    i = p / t.tri_count
    first_tri = t.tri_start + p - i * t.tri_count
    visits = int(0)
    skipped = int(0)
    while p < last:
        n = wp.min(last - p, t.tri_start + t.tri_count - first_tri)  # pairs of ray i here
        ray = d.ray_ids[t.ray_start + i]
        rec = d.io.rays[ray]
        w = widened_range(rec)
        span = ray_span(rec, t.lo, t.hi, w[0], w[1])
        # Most rays of an intersection task are clipped by its box or already hit nearer
        # (bunny 1024²: 79% of them): those skip the ray set-up too, not only the pairs.
        if span[0] < INF and not key_t(d.io.best[ray]) < span[0]:
            r = make_ray(rec.origin, d.io.directions[ray])
            key = KEY_NONE
            for j in range(first_tri, first_tri + n):
                tri = d.tri_ids[j]
                h = intersect_triangle(r, d.io.tri_verts[3 * tri], d.io.tri_verts[3 * tri + 1],
                                       d.io.tri_verts[3 * tri + 2], rec.tmin, rec.tmax)
                if h[0] < INF:
                    key = wp.min(key, hit_key(h[0], tri))
            if key != KEY_NONE:
                shared_min_u64(d.io.best, ray, key)
        else:
            skipped += 1
        visits += 1
        p += n
        i += 1
        first_tri = t.tri_start
    shared_add(d.counters, C_VISITS, visits)
    shared_add(d.counters, C_SKIPPED, skipped)


@wp.func(inline=False)  # inlined into both callers, the worker's PPS and Swap ran ~2x slower
def run_chunks(d: DacrtData, worker: int, slot: int, t: DacrtTask, first: int, count: int):
    """Chunks first.. of the task's step (the worker's `run_chunks`). One call per batch, as
    the call copies the structs."""
    if t.phase == PH_INTERSECT:
        intersect_chunks(d, t, first, count)
        return
    for chunk in range(first, first + count):
        if t.phase == PH_SPLIT_PLANE:
            split_plane_chunk(d, t, slot, chunk)
        elif t.phase == PH_SORT:
            sort_small_task(d, t, slot)
        else:
            # chunks of the segments one after another
            c = chunk
            top = segment_levels(t)
            for k in range(t.seg.count):
                n = segment_chunks(t, k, top)
                if c >= 0 and c < n:
                    if t.phase == PH_PPS1 or t.phase == PH_PPS2:
                        pps_chunk(d, t, slot, k, c)
                    elif t.phase == PH_SWAP1 or t.phase == PH_SWAP2:
                        swap_chunk(d, t, k, c)
                    else:
                        aabb_chunk(d, t, k, c)
                c -= n


@wp.func
def enter(d: DacrtData, t: DacrtTask, phase: int) -> DacrtTask:
    t.phase = phase
    t.step = 0
    t.chunks = step_chunks(d, t)
    return t


@wp.func
def enter_pps1(d: DacrtData, t: DacrtTask) -> DacrtTask:
    shared_add(d.counters, C_RAYS_SORTED, t.ray_count)
    shared_add(d.counters, C_TRIS_SORTED, t.tri_count)
    if t.ray_count + t.tri_count <= d.small_items:
        return enter(d, t, PH_SORT)
    s = Segment3()
    s.count = 0
    s = add_segment(s, 0, t.ray_start, t.ray_count, ROLE_RAYS)
    s = add_segment(s, 1, t.tri_start, t.tri_count, ROLE_TRIS)
    t.seg = s
    return enter(d, t, PH_PPS1)


@wp.func
def terminate(d: DacrtData, n_tris: int, n_rays: int) -> bool:
    """sec. 5.2: #tris #rays C_INTERS < (#tris + #rays) C_SORT, or few rays or triangles."""
    cost = float(n_tris) * float(n_rays) * d.c_inters
    return (cost < float(n_tris + n_rays) * d.c_sort or n_rays < d.min_rays
            or n_tris < d.min_tris)


@wp.func
def make_leaf(d: DacrtData, t: DacrtTask) -> DacrtTask:
    t.leaf = 1
    pairs = float(t.ray_count) * float(t.tri_count)
    if pairs > 2.0e9:
        shared_add(d.counters, C_OVERFLOW, 1)
        t.ray_count = 0
    shared_add(d.counters, C_KPAIRS, int(pairs / 1000.0 + 0.5))
    return enter(d, t, PH_INTERSECT)


@wp.func
def new_task(d: DacrtData, ray_start: int, ray_count: int, tri_start: int, tri_count: int,
             depth: int, lo: wp.vec3, hi: wp.vec3) -> DacrtTask:
    """A task ready for its first step; the median plane is chosen here."""
    t = DacrtTask()
    t.ray_start = ray_start
    t.ray_count = ray_count
    t.tri_start = tri_start
    t.tri_count = tri_count
    t.depth = depth
    t.lo = lo
    t.hi = hi
    t.leaf = 0
    t.tries = 0
    t.nsucc = 0
    t.seg = Segment3()
    if terminate(d, tri_count, ray_count) or depth >= d.max_depth:
        return make_leaf(d, t)
    if d.split_method == SPLIT_RDH and ray_count >= d.rdh_min_rays:
        return enter(d, t, PH_SPLIT_PLANE)
    plane = median_plane(lo, hi)
    t.axis = int(plane[0])
    t.split = plane[1]
    return enter_pps1(d, t)


@wp.func
def complete_step(d: DacrtData, t: DacrtTask, slot: int) -> DacrtTask:
    """The last finisher interprets the step's results and moves the task on (the worker's
    `complete_step`)."""
    if t.phase == PH_INTERSECT:
        t.phase = PH_DONE
        return t
    if t.phase == PH_SPLIT_PLANE and t.step == 1:
        return enter_pps1(d, choose_rdh_split(d, t, slot))
    if t.phase == PH_SPLIT_PLANE:
        rdh_children(d, t, slot, 0)  # the rays' step needs the children's boxes
    if t.phase == PH_SORT:
        return sort_result(d, t, slot)
    if t.phase == PH_PPS1 or t.phase == PH_PPS2:
        top = segment_levels(t)
        if t.step == top - 1:
            t = pps_top(d, t)
        if t.step == 2 * top - 2:
            return enter(d, pps_end(d, t), t.phase + 1)
    elif t.phase == PH_SWAP1 and t.step == 1:
        return enter_pps2(d, t)
    elif t.phase == PH_SWAP2 and t.step == 1:
        return enter_aabb(d, t)
    elif t.phase == PH_AABB and t.step == segment_levels(t) - 1:
        return aabb_result(d, t)
    t.step += 1
    t.chunks = step_chunks(d, t)
    return t


@wp.func
def enter_pps2(d: DacrtData, t: DacrtTask) -> DacrtTask:
    """Swap1 left [left + straddling | right + clipped] rays and [left + straddling | right]
    triangles; PPS2 splits the front parts, and the rays' back part (sec. 5.2)."""
    ray_front = int(0)
    tri_front = int(0)
    for k in range(t.seg.count):
        if t.seg.role[k] == ROLE_RAYS:
            ray_front = t.seg.pivot[k]
        else:
            tri_front = t.seg.pivot[k]
    t.rays = wp.vec4i(ray_front, 0, t.ray_count - ray_front, 0)
    t.tris = wp.vec3i(tri_front, 0, t.tri_count - tri_front)
    s = Segment3()
    s.count = 0
    s = add_segment(s, 0, t.ray_start, ray_front, ROLE_RAYS_LEFT)
    s = add_segment(s, 0, t.ray_start + ray_front, t.ray_count - ray_front, ROLE_RAYS_RIGHT)
    s = add_segment(s, 1, t.tri_start, tri_front, ROLE_TRIS_LEFT)
    t.seg = s
    return enter(d, t, PH_PPS2)


@wp.func
def retry(d: DacrtData, t: DacrtTask) -> DacrtTask:
    """Nothing separated: try the midplanes of the other two axes, then intersect here."""
    t.tries += 1
    if t.tries >= 3:
        return make_leaf(d, t)
    t.axis = (t.axis + 1) % 3
    t.split = 0.5 * (t.lo[t.axis] + t.hi[t.axis])
    return enter_pps1(d, t)


@wp.func
def sort_small_task(d: DacrtData, t: DacrtTask, slot: int):
    """PPS1 to AABB of a task of at most small_items rays and triangles, in the worker that
    runs it: classify, count per class, and place each class at its offset through Swap's
    arrays (a counting sort: rays [left | straddling | right | clipped], triangles [left |
    straddling | right], the layout the two PPS/Swap rounds make), with the triangle boxes
    on the way. Counts and boxes go to the slot's RDH sample area (free: the task's own
    sampling, if any, is over and cleared it), where sort_result takes and clears them."""
    ints = slot * CAND_INTS
    boxes = slot * CAND_BOXES
    n_ray = wp.vec4i(0)
    neg = int(0)
    end = t.ray_start + t.ray_count
    for i in range(t.ray_start, end):
        if i + PREFETCH < end:
            prefetch_ray(d.io.rays, d.io.best, d.ray_ids[i + PREFETCH])
        ray = d.ray_ids[i]
        r = d.io.rays[ray]
        c = classify_ray(d, t, ray, r)
        d.ray_mark[i] = wp.int8(c)  # by position: read in order below
        n_ray[c] = n_ray[c] + 1
        if c == CLS_STRADDLE and r.inv_dir[t.axis] < 0.0:
            neg += 1
    at = wp.vec4i(0, n_ray[0], n_ray[0] + n_ray[1], n_ray[0] + n_ray[1] + n_ray[2])
    for i in range(t.ray_start, t.ray_start + t.ray_count):
        c = int(d.ray_mark[i])
        d.ray_swap_id[t.ray_start + at[c]] = d.ray_ids[i]
        at[c] = at[c] + 1
    for i in range(t.ray_start, t.ray_start + t.ray_count):
        d.ray_ids[i] = d.ray_swap_id[i]
    n_tri = wp.vec3i(0)
    end = t.tri_start + t.tri_count
    for i in range(t.tri_start, end):
        if i + PREFETCH < end:
            prefetch_tri(d.io.tri_lo, d.io.tri_hi, d.tri_ids[i + PREFETCH])
        tri = d.tri_ids[i]
        c = classify_tri(d, t, tri)
        d.tri_mark[i] = wp.int8(c)
        n_tri[c] = n_tri[c] + 1
    at3 = wp.vec3i(0, n_tri[0], n_tri[0] + n_tri[1])
    lo = wp.matrix_from_rows(wp.vec3(INF), wp.vec3(INF), wp.vec3(INF))  # a box per class
    hi = wp.matrix_from_rows(wp.vec3(-INF), wp.vec3(-INF), wp.vec3(-INF))
    for i in range(t.tri_start, t.tri_start + t.tri_count):
        tri = d.tri_ids[i]
        c = int(d.tri_mark[i])
        d.tri_swap_id[t.tri_start + at3[c]] = tri
        at3[c] = at3[c] + 1
        lo[c] = min3(lo[c], d.io.tri_lo[tri])
        hi[c] = max3(hi[c], d.io.tri_hi[tri])
    for i in range(t.tri_start, t.tri_start + t.tri_count):
        d.tri_ids[i] = d.tri_swap_id[i]
    for k in range(4):
        d.cand[ints + k] = n_ray[k]
    for k in range(3):
        d.cand[ints + 4 + k] = n_tri[k]
        d.cand_lo[boxes + k] = lo[k]
        d.cand_hi[boxes + k] = hi[k]
    d.neg[slot] = neg


@wp.func
def sort_result(d: DacrtData, t: DacrtTask, slot: int) -> DacrtTask:
    """Take sort_small_task's counts and boxes (and clear the area for RDH)."""
    ints = slot * CAND_INTS
    boxes = slot * CAND_BOXES
    for k in range(4):
        t.rays[k] = d.cand[ints + k]
        d.cand[ints + k] = 0
    for k in range(3):
        t.tris[k] = d.cand[ints + 4 + k]
        d.cand[ints + 4 + k] = 0
        t.box_lo[k] = d.cand_lo[boxes + k]
        t.box_hi[k] = d.cand_hi[boxes + k]
        d.cand_lo[boxes + k] = wp.vec3(INF)
        d.cand_hi[boxes + k] = wp.vec3(-INF)
    if t.rays[1] == t.ray_count and t.tris[1] == t.tri_count:
        return retry(d, t)
    t.phase = PH_DONE
    return t


@wp.func
def enter_aabb(d: DacrtData, t: DacrtTask) -> DacrtTask:
    """Counts of the four ray and three triangle intervals; then the boxes of the three
    triangle intervals, unless the split made no progress (then intersect here)."""
    for k in range(t.seg.count):
        n = t.seg.size[k]
        p = t.seg.pivot[k]
        if t.seg.role[k] == ROLE_RAYS_LEFT:
            t.rays[0] = p
            t.rays[1] = n - p
        elif t.seg.role[k] == ROLE_RAYS_RIGHT:
            t.rays[2] = p
            t.rays[3] = n - p
        else:
            t.tris[0] = p
            t.tris[1] = n - p
    if t.rays[1] == t.ray_count and t.tris[1] == t.tri_count:
        return retry(d, t)
    s = Segment3()
    s.count = 0
    s = add_segment(s, 1, t.tri_start, t.tris[0], ROLE_BOX)
    s = add_segment(s, 1, t.tri_start + t.tris[0], t.tris[1], ROLE_BOX + 1)
    s = add_segment(s, 1, t.tri_start + t.tris[0] + t.tris[1], t.tris[2], ROLE_BOX + 2)
    t.seg = s
    return enter(d, t, PH_AABB)


@wp.func
def aabb_result(d: DacrtData, t: DacrtTask) -> DacrtTask:
    for k in range(3):
        t.box_lo[k] = wp.vec3(INF)
        t.box_hi[k] = wp.vec3(-INF)
    for k in range(t.seg.count):
        box = reduced_box(d.box_lo, d.box_hi, t.seg.start[k], t.seg.size[k])
        which = t.seg.role[k] - ROLE_BOX
        t.box_lo[which] = box[0]
        t.box_hi[which] = box[1]
    t.phase = PH_DONE
    return t


# ---------------------------------------------------------------- children (sec. 5.3)


@wp.func
def child_box(d: DacrtData, t: DacrtTask, ray_side: int, tri_side: int) -> wp.mat33:
    """The half of the node box the pair can meet in, cut to its triangles' box, widened."""
    lo = wp.max(t.lo, t.box_lo[tri_side])
    hi = wp.min(t.hi, t.box_hi[tri_side])
    if ray_side == CLS_LEFT or tri_side == CLS_LEFT:
        hi[t.axis] = wp.min(hi[t.axis], t.split)
    if ray_side == CLS_RIGHT or tri_side == CLS_RIGHT:
        lo[t.axis] = wp.max(lo[t.axis], t.split)
    return widen(lo, hi, d.io.margin)


@wp.func
def finish_task(d: DacrtData, pool: Pool, worker: int, t: DacrtTask, slot: int) -> int:
    """A finished intersection task releases its slot and activates its dependants; a
    finished subdivision stores its children. Returns a locked slot to continue with, or -1."""
    if t.leaf != 0:
        shared_add(d.counters, C_LEAVES, 1)
        pool_release(pool, slot)
        return activate(d, pool, t)
    return spawn_children(d, pool, t, slot)


@wp.func
def activate(d: DacrtData, pool: Pool, t: DacrtTask) -> int:
    keep = int(-1)
    for k in range(t.nsucc):
        s = t.succ[k]
        if pool_resolve(pool, s):
            if keep < 0:
                keep = s
            else:
                pool_publish(pool, s, wp.max(d.tasks[s].chunks, 1))  # 0 would mean locked
    return keep


@wp.func
def spawn_children(d: DacrtData, pool: Pool, t: DacrtTask, slot: int) -> int:
    """Store the (up to) seven children of the look-up table (sec. 5.3): successors first,
    dependants with their counts, the last group inheriting the parent's dependants. Rays
    mostly heading to -axis make the right side 'near', so straddling rays meet near
    triangles first (T3 before T5). Continues with the first active child."""
    flip = 2 * d.neg[slot] > t.rays[1]
    ray_n = wp.vec3i(t.rays[0], t.rays[1], t.rays[2])
    tri_n = t.tris
    ray_first = wp.vec3i(t.ray_start, t.ray_start + t.rays[0],
                         t.ray_start + t.rays[0] + t.rays[1])
    tri_first = wp.vec3i(t.tri_start, t.tri_start + t.tris[0],
                         t.tri_start + t.tris[0] + t.tris[1])
    mask = int(0)
    for i in range(3):
        side = i
        if flip and i != 1:
            side = 2 - i
        if ray_n[side] == 0:
            mask |= 1 << i
        if tri_n[side] == 0:
            mask |= 1 << (3 + i)
    row = mask * TABLE
    count = d.table[row + T_COUNT]
    if count == 0:
        pool_release(pool, slot)
        return activate(d, pool, t)
    sinks = d.table[row + T_SINKS]
    for k in range(t.nsucc):  # the sinks now finish for the parent: sinks - 1 more to wait on
        shared_add(pool.header, t.succ[k], 1 - sinks)
    slots = Slots7()
    keep = int(-1)
    depth = t.depth + 1
    for j in range(count):
        task_id = d.table[row + T_ORDER + j]
        rs = RAY_INTERVAL[task_id]
        ts = TRI_INTERVAL[task_id]
        if flip:
            rs = 2 - rs
            ts = 2 - ts
        box = child_box(d, t, rs, ts)
        c = new_task(d, ray_first[rs], ray_n[rs], tri_first[ts], tri_n[ts], depth, box[0],
                     box[1])
        if d.table[row + T_IS_SINK + task_id] != 0:
            c.succ = t.succ
            c.nsucc = t.nsucc
        else:
            c.nsucc = 0
            for k in range(MAX_SUCC):
                y = d.table[row + T_SUCC + task_id * MAX_SUCC + k]
                if y >= 0:
                    c.succ[c.nsucc] = slots[y]
                    c.nsucc += 1
        s = slot
        if j > 0:
            s = pool_alloc(pool)
            if s < 0:
                return -1
        slots[task_id] = s
        d.neg[s] = 0
        d.tasks[s] = c
        shared_add(d.counters, C_TASKS, 1)
        preds = d.table[row + T_PREDS + task_id]
        if preds > 0:
            pool_wait(pool, s, preds)
        elif keep < 0:
            keep = s
        else:
            pool_publish(pool, s, wp.max(c.chunks, 1))  # 0 would mean locked
    shared_max(d.counters, C_MAX_DEPTH, depth)
    return keep


# ---------------------------------------------------------------- the worker


dacrt_worker = make_worker(Application(
    data=DacrtData, task=DacrtTask, run_chunks=run_chunks, complete_step=complete_step,
    finish_task=finish_task, done=PH_DONE, module=__name__, name="dacrt"))


@wp.kernel
def start_trace(d: DacrtData, pool: Pool, lo: wp.vec3, hi: wp.vec3, rays: int, tris: int):
    """Store the root task: every ray, every (non-degenerate) triangle, the scene box."""
    slot = pool_alloc(pool)
    t = new_task(d, 0, rays, 0, tris, 0, lo, hi)
    t.nsucc = 0
    d.neg[slot] = 0
    d.tasks[slot] = t
    pool_publish(pool, slot, wp.max(t.chunks, 1))


# ---------------------------------------------------------------- host side


def pool_trace(mesh: DeviceMesh, origins, directions, tmin, tmax, margin: float, split: str,
               info: DacrtStats, opts: DacrtOptions, capacity: int) -> Hits:
    """The task-pool trace of validated rays with `capacity` pool slots (`opts` resolved for
    the mesh's device); fills `info` with its statistics."""
    device = mesh.device
    ids = mesh.valid_ids()
    t_start = time.perf_counter()
    mem = DeviceArrays(device)
    r, m, n = len(origins), len(mesh.indices), len(ids)
    io = rays_and_triangles(mem, mesh, origins, directions, tmin, tmax)
    io.best = mem.new(max(r, 1), wp.uint64, fill=KEY_NONE)
    io.margin = margin
    d = DacrtData()
    d.io = io
    d.ray_ids = mem.new(max(r, 1), int, data=np.arange(max(r, 1), dtype=np.int32))
    d.tri_ids = mem.new(max(n, 1), int, data=ids if n else np.zeros(1, np.int32))
    for name, size, dtype in (("ray_cls", r, wp.int8), ("ray_mark", r, wp.int8),
                              ("ray_scan", r, int), ("ray_swap_id", r, int),
                              ("ray_swap_pos", r, int), ("tri_cls", m, wp.int8),
                              ("tri_mark", n, wp.int8), ("tri_scan", n, int),
                              ("tri_swap_id", n, int), ("tri_swap_pos", n, int),
                              ("box_lo", n, wp.vec3), ("box_hi", n, wp.vec3)):
        setattr(d, name, mem.new(max(size, 1), dtype))
    d.cand = mem.new(capacity * CAND_INTS, wp.int32, fill=0)
    d.cand_lo = mem.new(capacity * CAND_BOXES, wp.vec3, fill=wp.vec3(np.inf))
    d.cand_hi = mem.new(capacity * CAND_BOXES, wp.vec3, fill=wp.vec3(-np.inf))
    d.neg = mem.new(capacity, wp.int32, fill=0)
    d.tasks = mem.new(capacity, DacrtTask)
    d.table = mem.new(table.MASKS * table.ROW, wp.int32, data=table.flat_table())
    d.counters = mem.new(COUNTERS, wp.int32, fill=0)
    workers = (default_workers(device, per_sm=WORKERS_PER_SM) if opts.workers is None
               else max(1, int(opts.workers)))
    d.phase_cycles = mem.new(workers * CYCLE_ROW, wp.int64, fill=0)
    d.split_method = SPLITS[split]
    d.rdh_min_rays = int(opts.rdh_min_rays)
    small_items = opts.small_items
    if small_items is None:
        small_items = max(SMALL_ITEMS_CPU, (r + n) // workers) if device.is_cpu else 0
    d.small_items = int(small_items)
    d.max_depth = int(opts.max_depth)
    d.c_inters = float(opts.c_inters)  # sec. 6.2: C_INTERS = 1, C_SORT = 80 (CUDA)
    d.c_sort = float(opts.c_sort)
    d.min_rays = int(opts.min_rays)  # sec. 6.2: 32 rays (CUDA), 16 triangles
    d.min_tris = int(opts.min_tris)
    pool = make_pool(capacity, workers, int(opts.min_chunks), device)
    mem.bytes += 2 * capacity * 4
    mem.peak = max(mem.peak, mem.bytes)
    prepare_ms = (time.perf_counter() - t_start) * 1e3

    t0 = time.perf_counter()
    if r and n:
        box_lo, box_hi = scene_box(mesh.vertices, mesh.indices, ids, margin)
        wp.launch(start_trace, dim=1,
                  inputs=[d, pool, wp.vec3(*box_lo), wp.vec3(*box_hi), r, n], device=device)
        launch_workers(dacrt_worker, workers, [d, pool], device)
    counters = d.counters.numpy()
    if counters[C_OVERFLOW]:
        raise RuntimeError("a DACRT leaf holds more than 2e9 ray-triangle pairs: the split "
                           "made no progress; lower max_depth or use variant='breadth_first'")
    state = check_pool(pool) if r and n else np.zeros(4, np.int32)
    wp.synchronize_device(device)
    trace_ms = (time.perf_counter() - t0) * 1e3

    t0 = time.perf_counter()
    hits = unpack_hits(mem, io, r)
    spent = d.phase_cycles.numpy().reshape(workers, CYCLE_ROW)[:, : len(PHASE_NAMES)]
    spent = spent.sum(axis=0).astype(np.float64)
    share = spent / spent.sum() if spent.sum() > 0 else np.zeros_like(spent)
    info.fill(
        variant="pool", split=split, total_ms=(time.perf_counter() - t_start) * 1e3,
        prepare_ms=prepare_ms, trace_ms=trace_ms,
        phase_ms={name: float(trace_ms * s) for name, s in zip(PHASE_NAMES, share, strict=True)},
        peak_bytes=int(mem.peak), tasks=int(counters[C_TASKS]) + 1,
        intersection_tasks=int(counters[C_LEAVES]), depth=int(counters[C_MAX_DEPTH]),
        rays_sorted=int(counters[C_RAYS_SORTED]), tris_sorted=int(counters[C_TRIS_SORTED]),
        pairs=1000 * int(counters[C_KPAIRS]), intersection_rays=int(counters[C_VISITS]),
        intersection_rays_skipped=int(counters[C_SKIPPED]), pool_slots_used=int(state[2]),
        workers=workers, small_items=small_items, degenerate=int(m - n))
    return hits


# the Warp modules a trace runs (loaded first: Warp's compile time is reported apart)
WARP_MODULES = (dacrt_worker.module, *records.WARP_MODULES, *core_mesh.WARP_MODULES,
                *clock.WARP_MODULES)
