"""Binned SAH for the BVH build's SplitPlane phase (2012 paper, sec. 4.1).

Each work chunk bins its triangles into BINS bins spanning the task's centroid box on its
longest axis; every bin keeps its triangles' box and its centroids' box. The last finisher
sweeps the BINS - 1 planes and takes the children's exact boxes from the bins.
"""

from __future__ import annotations

import warp as wp

from ..core.atomics import shared_add, shared_max_vec3, shared_min_vec3
from ..core.box import INF, half_area, max3, min3
from ..pool.chunks import CHUNK
from .build_data import BINS, BinFloats, BuildData, BuildTask


@wp.func
def bin_scale(t: BuildTask) -> float:
    """Bins per unit length along the split axis of the task's centroid box."""
    return float(BINS) / (t.chi[t.axis] - t.clo[t.axis])


@wp.func
def bin_of(c: float, lo: float, scale: float) -> int:
    """SAH bin of a centroid coordinate: the same float expression in SplitPlane and PPS."""
    return wp.clamp(int((c - lo) * scale), 0, BINS - 1)


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
    base = bin_slot * BINS
    for i in range(first, last):
        it = b.items[i]
        lo = it.lo
        hi = it.hi
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
    src = from_slot * BINS
    dst = to_slot * BINS
    for k in range(BINS):
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
    base = slot * BINS
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
