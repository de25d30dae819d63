"""Task-pool divide-and-conquer ray tracing (2012 paper, sec. 5).

No acceleration structure: a task holds a node box, an interval of the ray index array and
one of the triangle index array. Two task kinds share the pool of `pool.py`:
  intersection   one step; each work chunk covers CHUNK ray-triangle pairs; the closest hit
                 per ray is an atomic min on a packed (t, triangle) key (deterministic)
  subdivision    SplitPlane (spatial median or RDH), PPS1, Swap1, PPS2, Swap2, AABB, then
                 seven children chosen from the dependency table (`dacrt_table.py`)
Rays are classified left / straddling / right / clipped against the plane within the node
box; triangles left / straddling / right by their boxes. A ray whose closest hit so far lies
before its entry into the node box is clipped too (ordered early termination). Boxes and
ray spans are widened by `margin`, so no hit that the watertight test reports is lost to
rounding.

PPS, Swap and AABB work on up to three segments at once (PPS2: the left and right ray parts
and the left triangle part); a step's chunks are the segments' chunks one after another.
"""

from __future__ import annotations

import warp as wp

from . import dacrt_table as tb
from .chunks import CHUNK, ceil_div, level_base, level_count, level_size
from .geometry import INF, intersect_triangle, make_ray, max3, min3, refine_hit
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
    pool_resolve,
    pool_running,
    pool_wait,
    shared_add,
    shared_max,
    shared_max_vec3,
    shared_min_vec3,
)

wp.set_module_options({"enable_backward": False, "optimization_level": 3})

CANDIDATES = wp.constant(32)  # RDH candidate planes over the three axes (sec. 5.2)
PLANES = wp.constant(33)  # ... and the spatial median as one more, so RDH can choose it
MEDIAN_TRUST = wp.constant(0.6)  # RDH keeps the median unless a candidate is 40% cheaper
CAND_INTS = 33 * 4  # per pool slot and plane: tris, then rays, of the left and right child
CAND_BOXES = 33 * 2  # per pool slot and plane: the sampled children's boxes
KEY_NONE = wp.constant(wp.uint64(0xFFFFFFFFFFFFFFFF))
PREFETCH = wp.constant(16)  # items ahead that the sort's classification loops prefetch
HASH_M1 = wp.constant(wp.uint32(0x7FEB352D))  # hash32's multipliers
HASH_M2 = wp.constant(wp.uint32(0x846CA68B))
T_WIDEN = wp.constant(1.0e-5)  # relative widening of [tmin, tmax] for classification

SPLIT_MEDIAN = wp.constant(0)
SPLIT_RDH = wp.constant(1)

PH_SPLIT_PLANE = wp.constant(0)
PH_PPS1 = wp.constant(1)
PH_SWAP1 = wp.constant(2)
PH_PPS2 = wp.constant(3)
PH_SWAP2 = wp.constant(4)
PH_AABB = wp.constant(5)
PH_INTERSECT = wp.constant(6)
PH_SORT = wp.constant(7)  # PPS1 to AABB of a small task in one worker (sort_small_task)
PH_DONE = wp.constant(8)
PHASE_NAMES = ("SplitPlane", "PPS1", "Swap1", "PPS2", "Swap2", "AABB", "Intersect", "Sort")
PHASES = wp.constant(8)

# element classes (ray_cls / tri_cls)
CLS_LEFT = wp.constant(0)
CLS_STRADDLE = wp.constant(1)
CLS_RIGHT = wp.constant(2)
CLS_CLIPPED = wp.constant(3)

# segment roles
ROLE_RAYS = wp.constant(0)  # PPS1: all rays, mark right or clipped
ROLE_TRIS = wp.constant(1)  # PPS1: all triangles, mark right
ROLE_RAYS_LEFT = wp.constant(2)  # PPS2: left/straddling rays, mark straddling
ROLE_RAYS_RIGHT = wp.constant(3)  # PPS2: right/clipped rays, mark clipped
ROLE_TRIS_LEFT = wp.constant(4)  # PPS2: left/straddling triangles, mark straddling
ROLE_BOX = wp.constant(5)  # AABB: one of the three triangle intervals

# counters[]
C_TASKS = wp.constant(0)
C_LEAVES = wp.constant(1)
C_MAX_DEPTH = wp.constant(2)
C_OVERFLOW = wp.constant(3)  # an intersection task with more than 2^31 pairs
C_RAYS_SORTED = wp.constant(4)  # rays entering PPS1, summed over subdivision tasks
C_KPAIRS = wp.constant(5)  # ray-triangle pairs of intersection tasks, in thousands
C_TRIS_SORTED = wp.constant(6)  # triangles entering PPS1, summed over subdivision tasks
C_VISITS = wp.constant(7)  # rays met by intersection tasks (per batch of chunks)
C_SKIPPED = wp.constant(8)  # ... of them clipped by the task's box or already hit nearer
COUNTERS = 9

TABLE = wp.constant(tb.ROW)  # row length of the flat dependency table, and its fields
T_COUNT = wp.constant(tb.COUNT)
T_SINKS = wp.constant(tb.SINKS)
T_ORDER = wp.constant(tb.ORDER)
T_PREDS = wp.constant(tb.PREDS)
T_IS_SINK = wp.constant(tb.IS_SINK)
T_SUCC = wp.constant(tb.SUCC)
MAX_SUCC = wp.constant(tb.MAX_SUCC)
Slots7 = wp.types.vector(length=7, dtype=wp.int32)
RAY_INTERVAL = wp.constant(Slots7(*(int(x) for x in tb.RAY_INTERVAL)))  # of T1..T7
TRI_INTERVAL = wp.constant(Slots7(*(int(x) for x in tb.TRI_INTERVAL)))


@wp.struct
class Segment3:
    """Up to three index-array segments that one PPS, Swap or AABB phase works on."""

    count: int  # segments in use
    is_tri: wp.vec3i  # 1: triangle index array, 0: ray index array
    start: wp.vec3i  # first position
    size: wp.vec3i
    role: wp.vec3i
    pivot: wp.vec3i  # after PPS: unmarked items (they stay in front)
    ones_left: wp.vec3i  # marked items in front of the pivot: what Swap exchanges


@wp.struct
class DacrtTask:
    ray_start: int
    ray_count: int
    tri_start: int
    tri_count: int
    depth: int
    phase: int
    step: int
    chunks: int
    leaf: int  # 1: intersection task
    tries: int  # planes that separated nothing (all rays and triangles straddling)
    lo: wp.vec3  # node box (widened by the margin)
    hi: wp.vec3
    axis: int
    split: float
    seg: Segment3
    rays: wp.vec4i  # rays left, straddling, right, clipped (after PPS2)
    tris: wp.vec3i  # triangles left, straddling, right
    box_lo: wp.mat33  # rows: boxes of the left, straddling, right triangles (after AABB)
    box_hi: wp.mat33
    succ: wp.vec2i  # slots this task activates when it finishes (sec. 5.3)
    nsucc: int


@wp.struct
class RayRecord:
    """What the box and plane tests read of a ray: 32 bytes, one cache line access per ray
    in the classification phases, where rays are visited in index-array order."""

    origin: wp.vec3
    tmin: float
    inv_dir: wp.vec3  # 1/d, +-inf where d == 0 (treated as parallel to that slab)
    tmax: float


@wp.struct
class DacrtData:
    rays: wp.array(dtype=RayRecord)  # per ray id
    directions: wp.array(dtype=wp.vec3)  # exact, for the triangle test
    tri_verts: wp.array(dtype=wp.vec3)  # v0, v1, v2 per triangle id
    tri_lo: wp.array(dtype=wp.vec3)
    tri_hi: wp.array(dtype=wp.vec3)
    ray_ids: wp.array(dtype=int)  # the ray index array
    tri_ids: wp.array(dtype=int)  # the triangle index array
    ray_cls: wp.array(dtype=wp.int8)  # per ray id, CLS_*
    tri_cls: wp.array(dtype=wp.int8)
    ray_mark: wp.array(dtype=wp.int8)  # per position: 1 = goes behind the pivot
    tri_mark: wp.array(dtype=wp.int8)
    ray_scan: wp.array(dtype=int)  # PPS levels packed inside each segment
    tri_scan: wp.array(dtype=int)
    ray_swap_id: wp.array(dtype=int)  # Swap's separate index arrays
    ray_swap_pos: wp.array(dtype=int)
    tri_swap_id: wp.array(dtype=int)
    tri_swap_pos: wp.array(dtype=int)
    box_lo: wp.array(dtype=wp.vec3)  # AABB levels, per triangle position
    box_hi: wp.array(dtype=wp.vec3)
    cand: wp.array(dtype=wp.int32)  # RDH sample counts, CAND_INTS per pool slot
    cand_lo: wp.array(dtype=wp.vec3)  # RDH children's boxes, CAND_BOXES per pool slot
    cand_hi: wp.array(dtype=wp.vec3)
    neg: wp.array(dtype=wp.int32)  # per slot: straddling rays heading to -axis
    best: wp.array(dtype=wp.uint64)  # per ray id: packed (t, triangle) of the closest hit
    tasks: wp.array(dtype=DacrtTask)
    table: wp.array(dtype=wp.int32)  # dacrt_table.flat_table()
    counters: wp.array(dtype=wp.int32)
    phase_cycles: wp.array(dtype=wp.int64)  # PHASES per worker
    split_method: int
    rdh_min_rays: int  # tasks with fewer rays take the median (cheaper than sampling)
    margin: float
    max_depth: int
    c_inters: float
    c_sort: float
    min_rays: int
    min_tris: int
    small_items: int  # tasks with at most this many rays + triangles sort in one worker


# ---------------------------------------------------------------- keys and atomics


@wp.func_native(
    """
union { float f; uint32_t u; } c;
c.f = t;
uint32_t b = (c.u & 0x80000000u) ? ~c.u : (c.u | 0x80000000u);
return ((uint64_t)b << 32) | (uint64_t)(uint32_t)tri;
"""
)
def hit_key(t: float, tri: int) -> wp.uint64:
    """(t, triangle) packed so that unsigned order is t order, then triangle order."""
    ...


@wp.func_native(
    """
uint32_t b = (uint32_t)(key >> 32);
union { float f; uint32_t u; } c;
c.u = (b & 0x80000000u) ? (b & 0x7FFFFFFFu) : ~b;
return c.f;
"""
)
def key_t(key: wp.uint64) -> float: ...


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    atomicMin((unsigned long long*)&a[i], (unsigned long long)v);
#else
    uint64_t old;
    __atomic_load(&a[i], &old, __ATOMIC_SEQ_CST);
    while (v < old && !__atomic_compare_exchange_n(&a[i], &old, v, false, __ATOMIC_SEQ_CST,
                                                   __ATOMIC_SEQ_CST)) {}
#endif
"""
)
def shared_min_u64(a: wp.array(dtype=wp.uint64), i: int, v: wp.uint64): ...


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


# ---------------------------------------------------------------- small helpers


@wp.func
def widen(lo: wp.vec3, hi: wp.vec3, m: float) -> wp.mat33:
    """Rows 0, 1: the box grown by m on every side."""
    return wp.matrix_from_rows(lo - wp.vec3(m), hi + wp.vec3(m), wp.vec3(0.0))


@wp.func
def infinite(x: float) -> bool:
    """wp.isinf compiles to a libm call on CPU (spilling every register around it)."""
    return wp.abs(x) == INF


@wp.func
def ray_span(r: RayRecord, lo: wp.vec3, hi: wp.vec3, tmin: float, tmax: float) -> wp.vec2:
    """(entry, exit) of the ray in [lo, hi] within [tmin, tmax]; entry inf on a miss."""
    t0 = tmin
    t1 = tmax
    for k in range(3):
        if infinite(r.inv_dir[k]):
            if r.origin[k] < lo[k] or r.origin[k] > hi[k]:
                return wp.vec2(INF, INF)
        else:
            a = (lo[k] - r.origin[k]) * r.inv_dir[k]
            b = (hi[k] - r.origin[k]) * r.inv_dir[k]
            enter = wp.where(a < b, a, b)  # selects, not wp.min: a third of the instructions
            leave = wp.where(a < b, b, a)
            t0 = wp.where(enter > t0, enter, t0)
            t1 = wp.where(leave < t1, leave, t1)
    if t0 <= t1:
        return wp.vec2(t0, t1)
    return wp.vec2(INF, INF)


@wp.func
def widened_range(r: RayRecord) -> wp.vec2:
    lo = r.tmin
    hi = r.tmax
    return wp.vec2(lo - T_WIDEN * wp.abs(lo), hi + T_WIDEN * wp.abs(hi))


@wp.func
def ray_side(r: RayRecord, span: wp.vec2, axis: int, split: float, m: float) -> int:
    """Side of the plane (widened by m) that the ray's points within the span lie on,
    compared in t: the plane's crossings (split -+ m - o) / d against the span's ends, so no
    division (the rounding of the products is a few ulps of t: far inside the margin)."""
    inv = r.inv_dir[axis]
    o = r.origin[axis]
    if infinite(inv):
        return side_of(wp.vec2(o, o), split, m)
    below = (split - m - o) * inv  # t where the ray crosses split - m
    above = (split + m - o) * inv
    if inv > 0.0:
        return CLS_STRADDLE + int(span[0] > above) - int(span[1] < below)
    return CLS_STRADDLE + int(span[1] < above) - int(span[0] > below)


@wp.func
def side_of(lo_hi: wp.vec2, split: float, m: float) -> int:
    if lo_hi[1] < split - m:
        return CLS_LEFT
    if lo_hi[0] > split + m:
        return CLS_RIGHT
    return CLS_STRADDLE


@wp.func
def classify_ray(d: DacrtData, t: DacrtTask, ray: int, r: RayRecord) -> int:
    """Left / straddling / right of the plane within the node box, or clipped: misses the
    box, or already hit something before entering it (sec. 5.2, PPS1)."""
    w = widened_range(r)
    span = ray_span(r, t.lo, t.hi, w[0], w[1])
    if span[0] == INF or key_t(d.best[ray]) < span[0]:
        return CLS_CLIPPED
    return ray_side(r, span, t.axis, t.split, d.margin)


@wp.func
def classify_tri(d: DacrtData, t: DacrtTask, tri: int) -> int:
    return side_of(wp.vec2(d.tri_lo[tri][t.axis], d.tri_hi[tri][t.axis]), t.split, 0.0)


# ---------------------------------------------------------------- segment storage


@wp.func
def get_id(d: DacrtData, is_tri: int, i: int) -> int:
    if is_tri != 0:
        return d.tri_ids[i]
    return d.ray_ids[i]


@wp.func
def get_mark(d: DacrtData, is_tri: int, i: int) -> int:
    if is_tri != 0:
        return int(d.tri_mark[i])
    return int(d.ray_mark[i])


@wp.func
def get_scan(d: DacrtData, is_tri: int, i: int) -> int:
    if is_tri != 0:
        return d.tri_scan[i]
    return d.ray_scan[i]


@wp.func
def set_scan(d: DacrtData, is_tri: int, i: int, x: int):
    if is_tri != 0:
        d.tri_scan[i] = x
    else:
        d.ray_scan[i] = x


@wp.func
def mark_item(d: DacrtData, t: DacrtTask, role: int, i: int) -> int:
    """Classify (PPS1) or look up (PPS2) the item at position i: bit 0 set if it goes
    behind the pivot, bit 1 for a straddling ray heading to -axis (PPS1)."""
    if role == ROLE_RAYS:
        ray = d.ray_ids[i]
        r = d.rays[ray]
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


# ---------------------------------------------------------------- PPS1 / PPS2


@wp.func
def pps_chunks(n: int, levels: int, top: int, step: int) -> int:
    """Chunks of one segment (with `levels` of its own, `top` the most of any segment) at
    this step: up-sweep at steps < levels, down-sweep aligned to end together."""
    if step < levels:
        return level_size(n, step + 1)
    if step >= top:
        level = 2 * top - 1 - step
        if level <= levels - 1:
            return level_size(n, level + 1)
    return 0


@wp.func
def pps_chunk(d: DacrtData, t: DacrtTask, slot: int, k: int, chunk: int):
    """One chunk of segment k (sec. 5.2, PPS1 and PPS2: the 32-ary PPS of sec. 4.1):
    up-sweep (level 1 marks and counts) or down-sweep."""
    is_tri = t.seg.is_tri[k]
    base = t.seg.start[k]
    n = t.seg.size[k]
    levels = level_count(n)
    top = segment_levels(t)
    if t.step < levels:
        level = t.step + 1
        total = int(0)
        if level == 1:
            first = base + chunk * CHUNK
            neg = int(0)
            for i in range(first, wp.min(first + CHUNK, base + n)):
                code = mark_item(d, t, t.seg.role[k], i)
                total += code & 1
                neg += code >> 1
            if neg > 0:  # one atomic per chunk, not per ray
                shared_add(d.neg, slot, neg)
        else:
            src = level_base(base, n, level - 1)
            m = level_size(n, level - 1)
            for i in range(chunk * CHUNK, wp.min(chunk * CHUNK + CHUNK, m)):
                total += get_scan(d, is_tri, src + i)
        set_scan(d, is_tri, level_base(base, n, level) + chunk, total)
    else:
        level = 2 * top - 1 - t.step
        src = level_base(base, n, level)
        m = level_size(n, level)
        running = get_scan(d, is_tri, level_base(base, n, level + 1) + chunk)
        for i in range(chunk * CHUNK, wp.min(chunk * CHUNK + CHUNK, m)):
            x = get_scan(d, is_tri, src + i)
            set_scan(d, is_tri, src + i, running)
            running += x


@wp.func
def ones_before(d: DacrtData, is_tri: int, base: int, n: int, local: int) -> int:
    """Marked items before local position `local` of a segment, from the PPS result."""
    c = local / CHUNK
    ones = int(0)
    if c < ceil_div(n, CHUNK):
        ones = get_scan(d, is_tri, base + c)
    for i in range(base + c * CHUNK, base + local):
        ones += get_mark(d, is_tri, i)
    return ones


@wp.func
def pps_top(d: DacrtData, t: DacrtTask) -> DacrtTask:
    """After the up-sweep: each segment's pivot; its top becomes the 0 offset."""
    for k in range(t.seg.count):
        n = t.seg.size[k]
        top = level_base(t.seg.start[k], n, level_count(n))
        t.seg.pivot[k] = n - get_scan(d, t.seg.is_tri[k], top)
        set_scan(d, t.seg.is_tri[k], top, 0)
    return t


# ---------------------------------------------------------------- Swap1 / Swap2


@wp.func
def swap_chunks(t: DacrtTask, k: int) -> int:
    n = t.seg.size[k]
    if t.step == 0:
        return ceil_div(n, CHUNK) - t.seg.pivot[k] / CHUNK
    return ceil_div(t.seg.pivot[k], CHUNK)


@wp.func
def swap_chunk(d: DacrtData, t: DacrtTask, k: int, chunk: int):
    """Step 0 gathers the unmarked items behind the pivot into the separate index array,
    step 1 trades them for the marked items in front of it (as Swap of sec. 4.1)."""
    is_tri = t.seg.is_tri[k]
    base = t.seg.start[k]
    pivot = t.seg.pivot[k]
    if t.step == 0:
        c = pivot / CHUNK + chunk
        ones = get_scan(d, is_tri, base + c)
        zeros_left = pivot - t.seg.ones_left[k]
        for j in range(c * CHUNK, wp.min(c * CHUNK + CHUNK, t.seg.size[k])):
            if get_mark(d, is_tri, base + j) != 0:
                ones += 1
            elif j >= pivot:
                r = base + (j - ones) - zeros_left
                if is_tri != 0:
                    d.tri_swap_id[r] = d.tri_ids[base + j]
                    d.tri_swap_pos[r] = base + j
                else:
                    d.ray_swap_id[r] = d.ray_ids[base + j]
                    d.ray_swap_pos[r] = base + j
    else:
        ones = get_scan(d, is_tri, base + chunk)
        for j in range(chunk * CHUNK, wp.min(chunk * CHUNK + CHUNK, pivot)):
            if get_mark(d, is_tri, base + j) != 0:
                item = get_id(d, is_tri, base + j)
                if is_tri != 0:
                    d.tri_ids[base + j] = d.tri_swap_id[base + ones]
                    d.tri_ids[d.tri_swap_pos[base + ones]] = item
                else:
                    d.ray_ids[base + j] = d.ray_swap_id[base + ones]
                    d.ray_ids[d.ray_swap_pos[base + ones]] = item
                ones += 1


# ---------------------------------------------------------------- AABB


@wp.func
def aabb_chunk(d: DacrtData, t: DacrtTask, k: int, chunk: int):
    """Box reduction of one triangle interval, one level per step (sec. 5.2, AABB)."""
    base = t.seg.start[k]
    n = t.seg.size[k]
    level = t.step + 1
    lo = wp.vec3(INF)
    hi = wp.vec3(-INF)
    if level == 1:
        first = base + chunk * CHUNK
        for i in range(first, wp.min(first + CHUNK, base + n)):
            tri = d.tri_ids[i]
            lo = min3(lo, d.tri_lo[tri])
            hi = max3(hi, d.tri_hi[tri])
    else:
        src = level_base(base, n, level - 1)
        first = src + chunk * CHUNK
        for i in range(first, wp.min(first + CHUNK, src + level_size(n, level - 1))):
            lo = min3(lo, d.box_lo[i])
            hi = max3(hi, d.box_hi[i])
    dst = level_base(base, n, level) + chunk
    d.box_lo[dst] = lo
    d.box_hi[dst] = hi


@wp.func
def aabb_chunks(t: DacrtTask, k: int) -> int:
    n = t.seg.size[k]
    if t.step < level_count(n):
        return level_size(n, t.step + 1)
    return 0


# ---------------------------------------------------------------- SplitPlane (RDH)


@wp.func
def median_plane(lo: wp.vec3, hi: wp.vec3) -> wp.vec2:
    """(axis, position): the middle of the box's longest axis."""
    e = hi - lo
    axis = int(0)
    if e[1] > e[axis]:
        axis = 1
    if e[2] > e[axis]:
        axis = 2
    return wp.vec2(float(axis), 0.5 * (lo[axis] + hi[axis]))


@wp.func
def axis_planes(t: DacrtTask) -> wp.vec3i:
    """RDH candidates on each axis: 32 in proportion to the node's extent (sec. 5.2)."""
    e = wp.max(t.hi - t.lo, wp.vec3(0.0))
    total = e[0] + e[1] + e[2]
    n = wp.vec3i(0, 0, 0)
    if total > 0.0:
        n[0] = int(float(CANDIDATES) * e[0] / total)
        n[1] = int(float(CANDIDATES) * e[1] / total)
    n[2] = CANDIDATES - n[0] - n[1]
    return n


@wp.func
def plane_pos(t: DacrtTask, axis: int, i: int, n: int) -> float:
    """The i-th of n planes uniformly spaced on the axis (non-decreasing in i)."""
    e = wp.max(t.hi[axis] - t.lo[axis], 0.0)
    return t.lo[axis] + e * (float(i) + 0.5) / float(n)


@wp.func
def candidate(t: DacrtTask, c: int) -> wp.vec2:
    """(axis, position) of RDH candidate c (axis by axis); c = CANDIDATES: the median."""
    if c == CANDIDATES:
        return median_plane(t.lo, t.hi)
    n = axis_planes(t)
    axis = int(0)
    i = c
    while i >= n[axis]:
        i -= n[axis]
        axis += 1
    return wp.vec2(float(axis), plane_pos(t, axis, i, n[axis]))


@wp.func
def planes_below(t: DacrtTask, axis: int, n: int, x: float, inclusive: int) -> int:
    """How many of the axis's n planes lie below x (at or below it if inclusive)."""
    lo = int(0)
    hi = n
    while lo < hi:
        mid = (lo + hi) / 2
        p = plane_pos(t, axis, mid, n)
        if p < x or (inclusive != 0 and p == x):
            lo = mid + 1
        else:
            hi = mid
    return lo


@wp.func
def sample_counts(t: DacrtTask) -> wp.vec2i:
    """N_T = sqrt(#tris), N_R = sqrt(#rays) samples (sec. 5.2)."""
    return wp.vec2i(wp.max(1, int(wp.sqrt(float(t.tri_count)))),
                    wp.max(1, int(wp.sqrt(float(t.ray_count)))))


@wp.func
def half_box(t: DacrtTask, lo: wp.vec3, hi: wp.vec3, axis: int, pos: float,
             right: int) -> wp.mat33:
    """Rows 0, 1: a triangle box cut to the node box and to one side of a plane."""
    blo = wp.max(lo, t.lo)
    bhi = wp.min(hi, t.hi)
    if right != 0:
        blo[axis] = wp.max(blo[axis], pos)
    else:
        bhi[axis] = wp.min(bhi[axis], pos)
    return wp.matrix_from_rows(blo, bhi, wp.vec3(0.0))


@wp.func
def hits_child(d: DacrtData, r: RayRecord, w: wp.vec2, k: int) -> bool:
    """Does the ray meet child box k (rdh_boxes)? An empty box is met by no ray.
    Monotone: a ray that meets a box meets every box around it."""
    lo = d.cand_lo[k]
    hi = d.cand_hi[k]
    if lo[0] > hi[0] or lo[1] > hi[1] or lo[2] > hi[2]:
        return False
    return ray_span(r, lo, hi, w[0], w[1])[0] < INF


@wp.func
def add_tri_sample(d: DacrtData, ints: int, boxes: int, c: int, right: int, lo: wp.vec3,
                   hi: wp.vec3):
    shared_add(d.cand, ints + 4 * c + right, 1)
    shared_min_vec3(d.cand_lo, boxes + 2 * c + right, lo)
    shared_max_vec3(d.cand_hi, boxes + 2 * c + right, hi)


@wp.func
def sample_tri(d: DacrtData, t: DacrtTask, ints: int, boxes: int, lo: wp.vec3, hi: wp.vec3):
    """A sampled triangle counts in the left child of the planes at or above its box's low
    end (a suffix of each axis's planes) and in the right child of those at or below its
    high end (a prefix): stored once, at the suffix's first and the prefix's last plane,
    and summed up by rdh_children."""
    n = axis_planes(t)
    first = int(0)
    for a in range(3):
        below = planes_below(t, a, n[a], lo[a], 0)
        if below < n[a]:
            add_tri_sample(d, ints, boxes, first + below, 0, lo, hi)
        upto = planes_below(t, a, n[a], hi[a], 1)
        if upto > 0:
            add_tri_sample(d, ints, boxes, first + upto - 1, 1, lo, hi)
        first += n[a]
    p = median_plane(t.lo, t.hi)
    side = side_of(wp.vec2(lo[int(p[0])], hi[int(p[0])]), p[1], 0.0)
    if side != CLS_RIGHT:
        add_tri_sample(d, ints, boxes, CANDIDATES, 0, lo, hi)
    if side != CLS_LEFT:
        add_tri_sample(d, ints, boxes, CANDIDATES, 1, lo, hi)


@wp.func
def sample_ray(d: DacrtData, t: DacrtTask, ints: int, boxes: int, r: RayRecord):
    """A sampled ray meets the left children of a suffix of each axis's planes (their boxes
    grow with the plane) and the right children of a prefix: two binary searches per axis,
    stored as for triangles."""
    w = widened_range(r)
    if ray_span(r, t.lo, t.hi, w[0], w[1])[0] == INF:
        return
    n = axis_planes(t)
    first = int(0)
    for a in range(3):
        for right in range(2):
            lo = int(0)  # first plane where the ray meets the left child / misses the right
            hi = n[a]
            while lo < hi:
                mid = (lo + hi) / 2
                c = first + mid
                if hits_child(d, r, w, boxes + 2 * c + right) == (right == 0):
                    hi = mid
                else:
                    lo = mid + 1
            if right == 0 and lo < n[a]:
                shared_add(d.cand, ints + 4 * (first + lo) + 2, 1)
            if right == 1 and lo > 0:
                shared_add(d.cand, ints + 4 * (first + lo - 1) + 3, 1)
        first += n[a]
    for right in range(2):
        if hits_child(d, r, w, boxes + 2 * CANDIDATES + right):
            shared_add(d.cand, ints + 4 * CANDIDATES + 2 + right, 1)


@wp.func
def hash32(x: int) -> int:
    """A well-mixed 31-bit hash of x (Wellons' lowbias32)."""
    h = wp.uint32(x)
    h = (h ^ (h >> wp.uint32(16))) * HASH_M1
    h = (h ^ (h >> wp.uint32(15))) * HASH_M2
    return int((h ^ (h >> wp.uint32(16))) >> wp.uint32(1))


@wp.func
def sample_position(t: DacrtTask, step: int, s: int) -> int:
    """Index-array position of SplitPlane's sample s at step 0 (triangles) or 1 (rays): one
    sample in each of n equal strata, at a hashed place in it. (A fixed stride aliases with
    the image's rows: at 1024² every one of the root's 1024 ray samples was a pixel of the
    first column.)"""
    n = sample_counts(t)[step]
    start = t.tri_start
    count = t.tri_count
    if step != 0:
        start = t.ray_start
        count = t.ray_count
    stride = count / n
    seed = hash32(hash32(t.ray_start) ^ t.tri_start) ^ (step << 30)  # the task's own offsets
    return start + s * stride + hash32(seed ^ s) % stride


@wp.func
def split_plane_chunk(d: DacrtData, t: DacrtTask, slot: int, chunk: int):
    """RDH sampling (sec. 5.2). Step 0: sampled triangles in the left and right child of
    every candidate, and the children's boxes. Step 1: sampled rays that meet each child's
    box: the ray distribution estimates how often a child is visited."""
    ns = sample_counts(t)
    ints = slot * CAND_INTS
    boxes = slot * CAND_BOXES
    if t.step == 0:
        for s in range(chunk * CHUNK, wp.min(chunk * CHUNK + CHUNK, ns[0])):
            tri = d.tri_ids[sample_position(t, 0, s)]
            sample_tri(d, t, ints, boxes, d.tri_lo[tri], d.tri_hi[tri])
    else:
        for s in range(chunk * CHUNK, wp.min(chunk * CHUNK + CHUNK, ns[1])):
            ray = d.ray_ids[sample_position(t, 1, s)]
            sample_ray(d, t, ints, boxes, d.rays[ray])


@wp.func
def rdh_children(d: DacrtData, t: DacrtTask, slot: int, field: int):
    """Turn what sample_tri (field 0) or sample_ray (field 2) stored at the ends of each
    axis's suffixes and prefixes into per-plane counts (and, for triangles, boxes)."""
    n = axis_planes(t)
    ints = slot * CAND_INTS
    boxes = slot * CAND_BOXES
    first = int(0)
    for a in range(3):
        count = int(0)
        lo = wp.vec3(INF)
        hi = wp.vec3(-INF)
        for c in range(first, first + n[a]):  # left children: sums over the suffixes
            count += d.cand[ints + 4 * c + field]
            d.cand[ints + 4 * c + field] = count
            if field == 0:
                lo = wp.min(lo, d.cand_lo[boxes + 2 * c])
                hi = wp.max(hi, d.cand_hi[boxes + 2 * c])
                d.cand_lo[boxes + 2 * c] = lo
                d.cand_hi[boxes + 2 * c] = hi
        count = int(0)
        lo = wp.vec3(INF)
        hi = wp.vec3(-INF)
        for j in range(n[a]):  # right children: the prefixes, from the axis's last plane
            c = first + n[a] - 1 - j
            count += d.cand[ints + 4 * c + field + 1]
            d.cand[ints + 4 * c + field + 1] = count
            if field == 0:
                lo = wp.min(lo, d.cand_lo[boxes + 2 * c + 1])
                hi = wp.max(hi, d.cand_hi[boxes + 2 * c + 1])
                d.cand_lo[boxes + 2 * c + 1] = lo
                d.cand_hi[boxes + 2 * c + 1] = hi
        first += n[a]
    if field == 0:
        for c in range(PLANES):  # the children's boxes: cut to the node and plane, widened
            p = candidate(t, c)
            for right in range(2):
                k = boxes + 2 * c + right
                box = half_box(t, d.cand_lo[k], d.cand_hi[k], int(p[0]), p[1], right)
                if box[0][0] <= box[1][0] and box[0][1] <= box[1][1] and box[0][2] <= box[1][2]:
                    box = widen(box[0], box[1], d.margin)
                d.cand_lo[k] = box[0]
                d.cand_hi[k] = box[1]


@wp.func
def choose_rdh_split(d: DacrtData, t: DacrtTask, slot: int) -> DacrtTask:
    """The cheapest candidate by the ray distribution heuristic (Bittner & Havran 2009):
    triangles of each child times the rays that meet its box, estimated from the samples.
    Clears the samples for the slot's next use."""
    rdh_children(d, t, slot, 2)
    base = slot * CAND_INTS
    boxes = slot * CAND_BOXES
    ns = sample_counts(t)
    tri_scale = float(t.tri_count) / float(ns[0])  # samples -> estimated counts
    ray_scale = float(t.ray_count) / float(ns[1])
    best = float(INF)
    for c in range(PLANES):
        k = base + 4 * c
        tl = tri_scale * float(d.cand[k])
        tr = tri_scale * float(d.cand[k + 1])
        rl = ray_scale * float(d.cand[k + 2])
        rr = ray_scale * float(d.cand[k + 3])
        # sec. 5.2's costs: the children's pairs, plus sorting what they hold (straddling
        # triangles and rays counted on both sides)
        cost = d.c_inters * (tl * rl + tr * rr) + d.c_sort * (tl + tr + rl + rr)
        if c == CANDIDATES:
            # the median, evaluated last, must lose clearly: the other costs come from
            # samples, and an estimate that is only a little lower is mostly noise
            cost *= MEDIAN_TRUST
        if cost < best:
            best = cost
            p = candidate(t, c)
            t.axis = int(p[0])
            t.split = p[1]
    for k in range(CAND_INTS):
        d.cand[base + k] = 0
    for k in range(CAND_BOXES):
        d.cand_lo[boxes + k] = wp.vec3(INF)
        d.cand_hi[boxes + k] = wp.vec3(-INF)
    return t


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
        if t.phase == PH_PPS1 or t.phase == PH_PPS2:
            total += pps_chunks(t.seg.size[k], level_count(t.seg.size[k]), top, t.step)
        elif t.phase == PH_SWAP1 or t.phase == PH_SWAP2:
            total += swap_chunks(t, k)
        elif t.phase == PH_AABB:
            total += aabb_chunks(t, k)
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
        rec = d.rays[ray]
        w = widened_range(rec)
        span = ray_span(rec, t.lo, t.hi, w[0], w[1])
        # Most rays of an intersection task are clipped by its box or already hit nearer
        # (bunny 1024²: 79% of them): those skip the ray set-up too, not only the pairs.
        if span[0] < INF and not key_t(d.best[ray]) < span[0]:
            r = make_ray(rec.origin, d.directions[ray])
            key = KEY_NONE
            for j in range(first_tri, first_tri + n):
                tri = d.tri_ids[j]
                h = intersect_triangle(r, d.tri_verts[3 * tri], d.tri_verts[3 * tri + 1],
                                       d.tri_verts[3 * tri + 2], rec.tmin, rec.tmax)
                if h[0] < INF:
                    key = wp.min(key, hit_key(h[0], tri))
            if key != KEY_NONE:
                shared_min_u64(d.best, ray, key)
        else:
            skipped += 1
        visits += 1
        p += n
        i += 1
        first_tri = t.tri_start
    shared_add(d.counters, C_VISITS, visits)
    shared_add(d.counters, C_SKIPPED, skipped)


@wp.func(inline=False)  # inlined into both callers, the worker's PPS and Swap ran ~2x slower
def run_chunks(d: DacrtData, t: DacrtTask, slot: int, first: int, count: int):
    """Chunks first.. of the task's step. One call per batch, as the call copies the
    structs."""
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
                n = int(0)
                if t.phase == PH_PPS1 or t.phase == PH_PPS2:
                    n = pps_chunks(t.seg.size[k], level_count(t.seg.size[k]), top, t.step)
                elif t.phase == PH_SWAP1 or t.phase == PH_SWAP2:
                    n = swap_chunks(t, k)
                else:
                    n = aabb_chunks(t, k)
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
    """The last finisher interprets the step's results and moves the task on."""
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
            for k in range(t.seg.count):
                t.seg.ones_left[k] = ones_before(d, t.seg.is_tri[k], t.seg.start[k],
                                                 t.seg.size[k], t.seg.pivot[k])
            return enter(d, t, t.phase + 1)
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
            prefetch_ray(d.rays, d.best, d.ray_ids[i + PREFETCH])
        ray = d.ray_ids[i]
        r = d.rays[ray]
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
            prefetch_tri(d.tri_lo, d.tri_hi, d.tri_ids[i + PREFETCH])
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
        lo[c] = min3(lo[c], d.tri_lo[tri])
        hi[c] = max3(hi[c], d.tri_hi[tri])
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
        n = t.seg.size[k]
        top = level_base(t.seg.start[k], n, level_count(n))
        which = t.seg.role[k] - ROLE_BOX
        t.box_lo[which] = d.box_lo[top]
        t.box_hi[which] = d.box_hi[top]
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
    return widen(lo, hi, d.margin)


@wp.func
def finish_task(d: DacrtData, pool: Pool, t: DacrtTask, slot: int) -> int:
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


@wp.func
def add_cycles(d: DacrtData, worker: int, phase: int, since: wp.int64):
    i = worker * PHASES + phase
    d.phase_cycles[i] = d.phase_cycles[i] + (cycles() - since)


@wp.func
def advance(d: DacrtData, pool: Pool, worker: int, slot: int, t: DacrtTask):
    """Run steps inline while they have fewer than K chunks (2012 paper, sec. 3.4), finishing
    tasks and continuing with a child or an activated dependant; publish the first step big
    enough for the pool."""
    s = slot
    task = t
    while True:
        phase = task.phase
        since = cycles()
        task = complete_step(d, task, s)
        if task.phase == PH_DONE:
            next_slot = finish_task(d, pool, task, s)
            add_cycles(d, worker, phase, since)
            if next_slot < 0:
                return
            s = next_slot
            task = d.tasks[s]
        else:
            add_cycles(d, worker, phase, since)
        if task.chunks >= pool.min_chunks:
            d.tasks[s] = task
            pool_hand_over(pool, s, task.chunks)
            return
        since = cycles()
        run_chunks(d, task, s, 0, task.chunks)
        add_cycles(d, worker, task.phase, since)


@wp.kernel
def dacrt_worker(d: DacrtData, pool: Pool, first_worker: int):
    """The persistent worker of Algorithm 1 (2012 paper, sec. 3.3)."""
    worker = first_worker + wp.tid()
    idle_since = wp.int64(-1)
    while pool_running(pool):
        got = pool_acquire(pool)
        slot = got[0]
        if slot < 0:
            idle_since = pool_idle(pool, idle_since)
            continue
        idle_since = wp.int64(-1)
        t = d.tasks[slot]
        since = cycles()
        run_chunks(d, t, slot, got[1], got[2])
        add_cycles(d, worker, t.phase, since)
        if pool_finish(pool, slot, got[2]):
            advance(d, pool, worker, slot, d.tasks[slot])


@wp.kernel
def start_trace(d: DacrtData, pool: Pool, lo: wp.vec3, hi: wp.vec3, rays: int, tris: int):
    """Store the root task: every ray, every (non-degenerate) triangle, the scene box."""
    slot = pool_alloc(pool)
    t = new_task(d, 0, rays, 0, tris, 0, lo, hi)
    t.nsucc = 0
    d.neg[slot] = 0
    d.tasks[slot] = t
    pool_publish(pool, slot, wp.max(t.chunks, 1))


@wp.kernel
def prepare_triangles(
    vertices: wp.array(dtype=wp.vec3),
    indices: wp.array(dtype=wp.vec3i),
    tri_verts: wp.array(dtype=wp.vec3),
    tri_lo: wp.array(dtype=wp.vec3),
    tri_hi: wp.array(dtype=wp.vec3),
):
    i = wp.tid()
    f = indices[i]
    a = vertices[f[0]]
    b = vertices[f[1]]
    c = vertices[f[2]]
    tri_verts[3 * i] = a
    tri_verts[3 * i + 1] = b
    tri_verts[3 * i + 2] = c
    tri_lo[i] = wp.min(wp.min(a, b), c)
    tri_hi[i] = wp.max(wp.max(a, b), c)


@wp.kernel
def prepare_rays(
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    tmin: wp.array(dtype=float),
    tmax: wp.array(dtype=float),
    rays: wp.array(dtype=RayRecord),
):
    i = wp.tid()
    d = directions[i]
    r = RayRecord()
    r.origin = origins[i]
    r.tmin = tmin[i]
    r.inv_dir = wp.vec3(1.0 / d[0], 1.0 / d[1], 1.0 / d[2])  # +-inf where d == 0
    r.tmax = tmax[i]
    rays[i] = r


@wp.kernel
def write_hits(
    tri_verts: wp.array(dtype=wp.vec3),
    rays: wp.array(dtype=RayRecord),
    directions: wp.array(dtype=wp.vec3),
    best: wp.array(dtype=wp.uint64),
    out_t: wp.array(dtype=float),
    out_triangle: wp.array(dtype=int),
    out_u: wp.array(dtype=float),
    out_v: wp.array(dtype=float),
):
    """Unpack the closest hit; t (and u, v) refined in float64 and clamped to the ray's range,
    as `kernels.trace` does."""
    i = wp.tid()
    key = best[i]
    out_t[i] = INF
    out_triangle[i] = -1
    out_u[i] = 0.0
    out_v[i] = 0.0
    if key == KEY_NONE:
        return
    tri = int(key & wp.uint64(0xFFFFFFFF))
    rec = rays[i]
    r = make_ray(rec.origin, directions[i])
    v0 = tri_verts[3 * tri]
    v1 = tri_verts[3 * tri + 1]
    v2 = tri_verts[3 * tri + 2]
    h = refine_hit(r, v0, v1, v2, rec.tmin, rec.tmax,
                   intersect_triangle(r, v0, v1, v2, rec.tmin, rec.tmax))
    out_t[i] = h[0]
    out_triangle[i] = tri
    out_u[i] = h[1]
    out_v[i] = h[2]
