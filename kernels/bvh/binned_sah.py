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
from .build_data import BINS, BinFloats, BuildData, BuildItem, BuildTask


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


# SplitPlane's binning of a worker's whole share on a CPU, as native code: the bins kept in
# registers and on the stack as 4-float vectors (a bin's box and centroid box in four
# min/max instructions, not twelve loads and stores through the arrays, which the compiler
# must assume alias the items), added to the arrays once at the end. The same float32
# operations as split_plane_chunk: the same bins. (x86-64 CPUs; elsewhere, CUDA included,
# it returns 0 and the chunks are binned one by one.)
BIN_RANGE_SOURCE = """
#if defined(__x86_64__) && !defined(__CUDA_ARCH__)
    typedef float f4 __attribute__((vector_size(4 * sizeof(float))));
    constexpr int N = BIN_COUNT;
    const float inf = __builtin_inff();
    f4 lo[N], hi[N], clo[N], chi[N];
    int count[N];
    for (int k = 0; k < N; ++k) {
        lo[k] = clo[k] = (f4){inf, inf, inf, inf};
        hi[k] = chi[k] = (f4){-inf, -inf, -inf, -inf};
        count[k] = 0;
    }
    const auto* it = items.data;
    const f4 half = {0.5f, 0.5f, 0.5f, 0.5f};
    for (int i = first; i < last; ++i) {
        const f4 a = {it[i].lo.c[0], it[i].lo.c[1], it[i].lo.c[2], 0.0f};
        const f4 b = {it[i].hi.c[0], it[i].hi.c[1], it[i].hi.c[2], 0.0f};
        const f4 c = half * (a + b);
        int k = (int)((c[axis] - origin) * scale);
        k = k < 0 ? 0 : (k > N - 1 ? N - 1 : k);
        count[k] += 1;
        // minps(x, y) is x < y ? x : y, maxps(x, y) x > y ? x : y: core.box's min3 / max3
        lo[k] = __builtin_ia32_minps(lo[k], a);
        hi[k] = __builtin_ia32_maxps(hi[k], b);
        clo[k] = __builtin_ia32_minps(clo[k], c);
        chi[k] = __builtin_ia32_maxps(chi[k], c);
    }
    for (int k = 0; k < N; ++k) {
        if (count[k] == 0)
            continue;
        bin_count.data[base + k] += count[k];
        float* out[4] = {bin_lo.data[base + k].c, bin_hi.data[base + k].c,
                         bin_clo.data[base + k].c, bin_chi.data[base + k].c};
        const f4* in[4] = {&lo[k], &hi[k], &clo[k], &chi[k]};
        for (int q = 0; q < 4; ++q)
            for (int a = 0; a < 3; ++a) {
                const float x = (*in[q])[a], y = out[q][a];
                out[q][a] = (q % 2 == 0) ? (y < x ? y : x) : (y > x ? y : x);
            }
    }
    return 1;
#else
    return 0;
#endif
""".replace("BIN_COUNT", str(int(BINS)))


@wp.func_native(BIN_RANGE_SOURCE)
def bin_range_native(items: wp.array(dtype=BuildItem), first: int, last: int, axis: int,
                     origin: float, scale: float, base: int, bin_count: wp.array(dtype=int),
                     bin_lo: wp.array(dtype=wp.vec3), bin_hi: wp.array(dtype=wp.vec3),
                     bin_clo: wp.array(dtype=wp.vec3),
                     bin_chi: wp.array(dtype=wp.vec3)) -> int:
    """Items [first, last) into the bins from `base` (BIN_RANGE_SOURCE); 0 where not
    compiled."""
    ...


@wp.func
def split_plane_chunks(b: BuildData, t: BuildTask, bin_slot: int, first: int, count: int):
    """SplitPlane's chunks first .. first + count - 1 into the bins of `bin_slot`: natively
    in one pass where bin_range_native runs, else chunk by chunk."""
    last = wp.min((first + count) * CHUNK, t.count)
    if bin_range_native(b.items, t.start + first * CHUNK, t.start + last, t.axis,
                        t.clo[t.axis], bin_scale(t), bin_slot * BINS, b.bin_count, b.bin_lo,
                        b.bin_hi, b.bin_clo, b.bin_chi) == 0:
        for c in range(first, first + count):
            split_plane_chunk(b, t, bin_slot, c)


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
