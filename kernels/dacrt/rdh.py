"""SplitPlane of task-pool DACRT: the ray distribution heuristic (2012 paper, sec. 5.2;
Bittner & Havran 2009).

CANDIDATES planes over the three axes, in proportion to the node's extent, and the spatial
median as one more: each is costed from sqrt(#tris) sampled triangles (the children's
triangle counts and boxes) and sqrt(#rays) sampled rays (how many meet each child's box).
Step 0 samples triangles, step 1 rays; the last finisher picks the cheapest plane.
"""

from __future__ import annotations

import warp as wp

from ..core.atomics import shared_add, shared_max_vec3, shared_min_vec3
from ..core.box import INF, median_plane
from ..pool.chunks import CHUNK
from .classify import CLS_LEFT, CLS_RIGHT, ray_span, side_of, widen, widened_range
from .records import RayRecord
from .task import CAND_BOXES, CAND_INTS, CANDIDATES, MEDIAN_TRUST, PLANES, DacrtData, DacrtTask

HASH_M1 = wp.constant(wp.uint32(0x7FEB352D))  # hash32's multipliers
HASH_M2 = wp.constant(wp.uint32(0x846CA68B))


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
            sample_tri(d, t, ints, boxes, d.io.tri_lo[tri], d.io.tri_hi[tri])
    else:
        for s in range(chunk * CHUNK, wp.min(chunk * CHUNK + CHUNK, ns[1])):
            ray = d.ray_ids[sample_position(t, 1, s)]
            sample_ray(d, t, ints, boxes, d.io.rays[ray])


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
                    box = widen(box[0], box[1], d.io.margin)
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
