"""The task record and data arrays of task-pool DACRT (2012 paper, sec. 5), shared by its
phases: a task holds a node box and an interval of the ray index array and of the triangle
index array."""

from __future__ import annotations

import warp as wp

from . import table as tb
from .records import TraceArrays

CANDIDATES = wp.constant(32)  # RDH candidate planes over the three axes (sec. 5.2)
PLANES = wp.constant(CANDIDATES + 1)  # ... and the spatial median, so RDH can choose it
MEDIAN_TRUST = wp.constant(0.6)  # RDH keeps the median unless a candidate is 40% cheaper
CAND_INTS = PLANES * 4  # per pool slot, per plane: tris, then rays, of the left and right child
CAND_BOXES = PLANES * 2  # per pool slot, per plane: the sampled children's boxes

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
PH_DONE = wp.constant(8)  # finished: its cycles are those of storing children (sec. 5.3)
PHASE_NAMES = ("SplitPlane", "PPS1", "Swap1", "PPS2", "Swap2", "AABB", "Intersect", "Sort",
               "Children")


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
class DacrtData:
    io: TraceArrays  # rays, triangles, closest hits (shared with the breadth-first variant)
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
    tasks: wp.array(dtype=DacrtTask)
    table: wp.array(dtype=wp.int32)  # dacrt_table.flat_table()
    counters: wp.array(dtype=wp.int32)
    phase_cycles: wp.array(dtype=wp.int64)  # per worker and phase (pool.worker.CYCLE_ROW)
    split_method: int
    rdh_min_rays: int  # tasks with fewer rays take the median (cheaper than sampling)
    max_depth: int
    c_inters: float
    c_sort: float
    min_rays: int
    min_tris: int
    small_items: int  # tasks with at most this many rays + triangles sort in one worker
