"""A round's statistics for the adaptive controller (`adaptive.py`), as Warp kernels over
every hit pixel: the pixels' estimated squared errors, the next round's allocation and the
bookkeeping of a round's samples.

Image-level sums are sums of blocks of BLOCK pixels, each block summed in pixel order by
one thread and the blocks' sums added in block order: the same bits on any number of host
threads (tested), and by construction on any device (run on the CPU only: the counts are
host arrays). The allocation's order is Warp's radix sort (stable). Arrays are kept between
rounds: at 3840x2160 numpy's fresh temporaries of the same passes cost 1.3-2.2 s a round
(notes/benchmarks-lab.md). The host keeps the scalars between passes and the cut.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..core.launch import host_threads, part_launcher, run_parts

BLOCK = wp.constant(4096)  # pixels per block sum: fixed, so no sum depends on the split
LAST_KEY = 8191  # allocation keys: 0..8191 for candidates (allocation_key), 8192 the rest
KEY_BITS = 14
PARTS_PER_THREAD = 4  # a pass's parts per host thread, taken in turn
MIN_PART_BLOCKS = 8  # ~0.5 ms of a pass: a part's launch costs ~20-50 us
Z95_VALUE = 1.959963984540054  # two-sided 95% normal quantile
Z95 = wp.constant(wp.float64(Z95_VALUE))


@wp.struct
class Sampler:
    """The sampler's measured step functions of a pixel's sample count n: value[j] for the
    j counts at or below n (value[0] below every count). Arrays for at least
    SAMPLER_CAPACITY counts, kept (grown when more are measured); `known` and `rates` of
    them in use."""

    counts: wp.array(dtype=wp.int64)  # sorted counts with a measured spread
    efficiency: wp.array(dtype=wp.float64)  # the sampler's efficiency (adaptive.py)
    spread: wp.array(dtype=wp.float64)  # the halves' spread itself (max_pixel_error's)
    known: int
    rho_counts: wp.array(dtype=wp.int64)  # sorted counts with a measured rate
    rho: wp.array(dtype=wp.float64)  # Var(2n) / Var(n), looked up at 2n
    rates: int


# Measured counts: a render's doublings from its minimum, at most ~30 (a fixed render's
# rounds all measure at its one count); the tables grow past this where more are given.
SAMPLER_CAPACITY = 64


@wp.func
def step_at(counts: wp.array(dtype=wp.int64), values: wp.array(dtype=wp.float64),
            used: int, n: wp.int64) -> wp.float64:
    """values[j] for the first j with counts[j] > n (j = used if none), by binary search."""
    lo = int(0)
    hi = used
    while lo < hi:
        mid = (lo + hi) / 2
        if counts[mid] > n:
            hi = mid
        else:
            lo = mid + 1
    return values[lo]


@wp.func
def sample_variance(k: wp.int64, n: wp.int64) -> wp.float64:
    """Unbiased variance of n 0/1 samples, k of them 1 (0 where they agree)."""
    nf = wp.float64(n)
    p = wp.float64(k) / nf
    return p * (wp.float64(1.0) - p) * nf / wp.max(nf - wp.float64(1.0), wp.float64(1.0))


@wp.func
def smoothed_variance(k: wp.int64, n: wp.int64) -> wp.float64:
    """sample_variance, but p(1-p) at the Jeffreys posterior mean where all samples agree."""
    if k == wp.int64(0) or k == n:
        q = (wp.float64(k) + wp.float64(0.5)) / (wp.float64(n) + wp.float64(1.0))
        return q * (wp.float64(1.0) - q)
    return sample_variance(k, n)


@wp.func
def posterior_variance(k: wp.int64, n: wp.int64, a: wp.float64, b: wp.float64,
                       prior: int) -> wp.float64:
    """E[p(1-p) | k of n] under the image's Beta(a, b) prior (the sample variance without)."""
    if prior == 0:
        return sample_variance(k, n)
    kf = wp.float64(k)
    nf = wp.float64(n)
    return (a + kf) * (b + nf - kf) / ((a + b + nf) * (a + b + nf + wp.float64(1.0)))


@wp.func
def block_range(block: int, count: int) -> wp.vec2i:
    return wp.vec2i(block * BLOCK, wp.min((block + 1) * BLOCK, count))


@wp.func
def octave16(g: wp.float32, powers: wp.array(dtype=wp.float64)) -> int:
    """A positive float32's bits >> 19 (8 exponent bits, the mantissa's first 4), by
    arithmetic (Warp has no bit cast); powers[e + 149] = 2^e."""
    x = wp.float64(g)
    if x < powers[149 - 126]:  # subnormal: the mantissa alone, x = m 2^-149
        return int(x * wp.float64(1.361129467683754e39))  # x 2^130 = m >> 19
    # log2 of a float32's value is at least 1e-7 from the next integer unless exact
    e = int(wp.floor(wp.log2(x)))
    top4 = int((x / powers[e + 149] - wp.float64(1.0)) * wp.float64(16.0))  # x / 2^e exact
    return (e + 127) * 16 + top4


@wp.func
def allocation_key(gain: wp.float32, under: bool, powers: wp.array(dtype=wp.float64)) -> int:
    """Doublings sort by this: below the Neyman count first, then by the variance removed
    per ray, `gain`, in steps of 1/16 octave (ties in pixel order: the sort is stable)."""
    key = 4095 - octave16(gain, powers)
    if not under:
        key += 4096
    return key


@wp.kernel
def image_sums(done: wp.array(dtype=wp.int64), opened: wp.array(dtype=wp.int64),
               sampler: Sampler, first: int, count: int,
               sums: wp.array2d(dtype=wp.float64)):
    """Per block: the pixels' estimates p and their sampling variances efficiency s^2 / n."""
    block = first + wp.tid()
    span = block_range(block, count)
    sp = wp.float64(0.0)
    sv = wp.float64(0.0)
    for i in range(span[0], span[1]):
        n, k = done[i], opened[i]
        eff = step_at(sampler.counts, sampler.efficiency, sampler.known, n)
        sp += wp.float64(k) / wp.float64(n)
        sv += eff * sample_variance(k, n) / wp.float64(n)
    sums[block, 0] = sp
    sums[block, 1] = sv


@wp.kernel
def deviation_sums(done: wp.array(dtype=wp.int64), opened: wp.array(dtype=wp.int64),
                   mean: wp.float64, first: int, count: int,
                   sums: wp.array2d(dtype=wp.float64)):
    """Per block: the estimates' squared deviations from their mean (the two-pass variance)."""
    block = first + wp.tid()
    span = block_range(block, count)
    s = wp.float64(0.0)
    for i in range(span[0], span[1]):
        d = wp.float64(opened[i]) / wp.float64(done[i]) - mean
        s += d * d
    sums[block, 0] = s


@wp.kernel
def contributions(done: wp.array(dtype=wp.int64), opened: wp.array(dtype=wp.int64),
                  sampler: Sampler, a: wp.float64, b: wp.float64, prior: int, first: int,
                  count: int, contribution: wp.array(dtype=wp.float64),
                  sums: wp.array2d(dtype=wp.float64)):
    """Each pixel's estimated squared error, efficiency * posterior variance / n; per
    block their sum."""
    block = first + wp.tid()
    span = block_range(block, count)
    s = wp.float64(0.0)
    for i in range(span[0], span[1]):
        n, k = done[i], opened[i]
        eff = step_at(sampler.counts, sampler.efficiency, sampler.known, n)
        c = eff * posterior_variance(k, n, a, b, prior) / wp.float64(n)
        contribution[i] = c
        s += c
    sums[block, 0] = s


@wp.func
def dropped(contribution: wp.float64, sampler: Sampler, n: wp.int64) -> wp.float64:
    """What doubling removes: all but rho(n) of the pixel's squared error."""
    return contribution * (wp.float64(1.0) - step_at(sampler.rho_counts, sampler.rho,
                                                     sampler.rates, wp.int64(2) * n))


@wp.func
def sigma(k: wp.int64, n: wp.int64, sampler: Sampler) -> wp.float64:
    """The Neyman allocation's sigma_i: sqrt(efficiency * smoothed variance)."""
    eff = step_at(sampler.counts, sampler.efficiency, sampler.known, n)
    return wp.sqrt(eff * smoothed_variance(k, n))


@wp.kernel
def allocation_sums(done: wp.array(dtype=wp.int64), opened: wp.array(dtype=wp.int64),
                    contribution: wp.array(dtype=wp.float64), sampler: Sampler,
                    max_spp: wp.int64, max_error: wp.float64, first: int, count: int,
                    want: wp.array(dtype=wp.uint8), sums: wp.array2d(dtype=wp.float64)):
    """want: pixels with room whose 95% half-width is >= max_error (none when it is < 0).
    Per block: what doubling the wanted removes, the squared error of pixels with room,
    the sigmas, and the pixels with room not yet wanted (the allocation's candidates)."""
    block = first + wp.tid()
    span = block_range(block, count)
    drop = wp.float64(0.0)
    room_error = wp.float64(0.0)
    sigmas = wp.float64(0.0)
    candidates = wp.float64(0.0)
    for i in range(span[0], span[1]):
        n, k = done[i], opened[i]
        w = wp.uint8(0)
        if n < max_spp:
            room_error += contribution[i]
            if max_error >= wp.float64(0.0):
                half = Z95 * wp.sqrt(step_at(sampler.counts, sampler.spread, sampler.known, n)
                                     * smoothed_variance(k, n) / wp.float64(n))
                if half >= max_error:
                    w = wp.uint8(1)
            if w == wp.uint8(1):
                drop += dropped(contribution[i], sampler, n)
            else:
                candidates += wp.float64(1.0)
        want[i] = w
        sigmas += sigma(k, n, sampler)
    sums[block, 0] = drop
    sums[block, 1] = room_error
    sums[block, 2] = sigmas
    sums[block, 3] = candidates


@wp.kernel
def allocation_keys(done: wp.array(dtype=wp.int64), opened: wp.array(dtype=wp.int64),
                    want: wp.array(dtype=wp.uint8), sampler: Sampler, max_spp: wp.int64,
                    neyman_scale: wp.float64, powers: wp.array(dtype=wp.float64),
                    first: int, count: int,
                    keys: wp.array(dtype=wp.int32), order: wp.array(dtype=wp.int32)):
    """Each candidate's allocation_key, LAST_KEY + 1 for the others; order: pixel index.
    A pixel is under its Neyman count sigma_i * neyman_scale by more than sqrt(2)."""
    block = first + wp.tid()
    span = block_range(block, count)
    for i in range(span[0], span[1]):
        n = done[i]
        key = LAST_KEY + 1
        if n < max_spp and want[i] == wp.uint8(0):
            s = sigma(opened[i], n, sampler)
            gain = wp.float32(s / wp.float64(n))
            under = s * neyman_scale > wp.float64(1.4142135623730951) * wp.float64(n)
            key = allocation_key(gain * gain, under, powers)
        keys[i] = key
        order[i] = i


@wp.kernel
def sorted_sums(order: wp.array(dtype=wp.int32), done: wp.array(dtype=wp.int64),
                contribution: wp.array(dtype=wp.float64), sampler: Sampler, first: int,
                count: int, sums: wp.array2d(dtype=wp.float64)):
    """Per block of the sorted candidates: what doubling them removes, the rays it traces."""
    block = first + wp.tid()
    span = block_range(block, count)
    drop = wp.float64(0.0)
    rays = wp.float64(0.0)
    for j in range(span[0], span[1]):
        i = order[j]
        drop += dropped(contribution[i], sampler, done[i])
        rays += wp.float64(done[i])
    sums[block, 0] = drop
    sums[block, 1] = rays


@wp.kernel
def sorted_values(order: wp.array(dtype=wp.int32), done: wp.array(dtype=wp.int64),
                  contribution: wp.array(dtype=wp.float64), sampler: Sampler, start: int,
                  values: wp.array2d(dtype=wp.float64)):
    """One block's sorted candidates one by one (sorted_sums' terms)."""
    j = wp.tid()
    i = order[start + j]
    values[j, 0] = dropped(contribution[i], sampler, done[i])
    values[j, 1] = wp.float64(done[i])


@wp.kernel
def mark(order: wp.array(dtype=wp.int32), want: wp.array(dtype=wp.uint8)):
    want[order[wp.tid()]] = wp.uint8(1)


@wp.func
def spread_terms(open_mid: wp.int64, n_mid: wp.int64, open_end: wp.int64, n_end: wp.int64
                 ) -> wp.vec3d:
    """One pixel's terms of the halves' spread (the sampler's efficiency: adaptive.py): the squared
    difference of its estimates after n_mid and n_end samples, their Bernoulli variance,
    and 1, where its samples disagree; zeros elsewhere."""
    if open_end > wp.int64(0) and open_end < n_end and n_mid > wp.int64(0) and n_end > n_mid:
        mid = wp.float64(n_mid)
        end = wp.float64(n_end)
        p = wp.float64(open_end) / end
        d = wp.float64(open_mid) / mid - p
        return wp.vec3d(d * d, p * (wp.float64(1.0) - p) * ((end - mid) / (mid * end)),
                        wp.float64(1.0))
    return wp.vec3d()


QUARTERS_NONE = 0  # record_round: no nested estimate at a quarter
QUARTERS_TRACED = 1  # counted in this launch
QUARTERS_KEPT = 2  # the pixels' `before` (their open samples at the previous half)


@wp.kernel
def record_round(select: wp.array(dtype=wp.int64), opened: wp.array(dtype=wp.int64),
                 opened_mid: wp.array(dtype=wp.int64),
                 opened_quarter: wp.array(dtype=wp.int64), end: wp.int64, mid: wp.int64,
                 quarters: int, first: int, count: int, done: wp.array(dtype=wp.int64),
                 open_total: wp.array(dtype=wp.int64), before: wp.array(dtype=wp.int64),
                 sums: wp.array2d(dtype=wp.float64)):
    """A launch's samples added to the selected pixels' counts (all at end - count before
    it); per block the spread terms of the halves (mid against end) and of the quarters
    (mid / 2 against mid)."""
    block = first + wp.tid()
    span = block_range(block, count)
    halves = wp.vec3d()
    quarter = wp.vec3d()
    for j in range(span[0], span[1]):
        i = select[j]
        now = open_total[i]
        at_mid = now + opened_mid[j]
        at_end = now + opened[j]
        halves += spread_terms(at_mid, mid, at_end, end)
        if quarters == QUARTERS_TRACED:
            quarter += spread_terms(now + opened_quarter[j], mid / wp.int64(2), at_mid, mid)
        elif quarters == QUARTERS_KEPT:
            quarter += spread_terms(before[i], mid / wp.int64(2), at_mid, mid)
        before[i] = at_mid
        open_total[i] = at_end
        done[i] = end
    for c in range(3):
        sums[block, c] = halves[c]
        sums[block, 3 + c] = quarter[c]


def powers_of_two() -> wp.array:
    """octave16's table: 2^e at e + 149, e in [-149, 128]."""
    return wp.array(np.ldexp(1.0, np.arange(-149, 129)), dtype=wp.float64, device="cpu")


class RoundStatistics:
    """The passes over the hit pixels' counts (numpy int64 arrays the rounds update in
    place), on host threads, with the arrays they write kept from round to round."""

    def __init__(self, done: np.ndarray, opened: np.ndarray, before: np.ndarray,
                 threads: int | None) -> None:
        self.device = wp.get_device("cpu")
        self.n = len(done)
        self.blocks = -(-self.n // BLOCK)
        self.threads = host_threads(self.device, threads)
        self.done = wp.array(done, dtype=wp.int64, device=self.device, copy=False)
        self.opened = wp.array(opened, dtype=wp.int64, device=self.device, copy=False)
        self.before = wp.array(before, dtype=wp.int64, device=self.device, copy=False)
        self.contribution = wp.empty(self.n, dtype=wp.float64, device=self.device)
        self.want = wp.empty(self.n, dtype=wp.uint8, device=self.device)
        self.sums = wp.empty((max(self.blocks, 1), 6), dtype=wp.float64, device=self.device)
        self.block_sums = self.sums.numpy()  # the same memory
        wp.load_module(image_sums.module, device=self.device)  # not in each thread at once
        self.keys = self.order = None  # the sort's, 2n each: made by the first that needs them
        self.terms = wp.empty((BLOCK, 2), dtype=wp.float64, device=self.device)  # one block's
        self.sampler = Sampler()
        self._make_tables(SAMPLER_CAPACITY)
        self.powers = powers_of_two()

    def _make_tables(self, capacity: int) -> None:
        """The kept Sampler's arrays, for `capacity` counts, and their numpy views."""
        tables = {"counts": wp.int64, "efficiency": wp.float64, "spread": wp.float64,
                  "rho_counts": wp.int64, "rho": wp.float64}
        for name, dtype in tables.items():
            setattr(self.sampler, name, wp.zeros(capacity + 1, dtype=dtype,
                                                 device=self.device))
        self.tables = {name: getattr(self.sampler, name).numpy() for name in tables}

    def measured(self, counts: list[int], efficiency: list[float], spread: list[float],
                 rho_counts: list[int], rho: list[float]) -> Sampler:
        """The kept Sampler, which every pass reads, holding these step functions (each
        value list one longer than its counts)."""
        need = max(len(counts), len(rho_counts))
        if need >= len(self.tables["counts"]):
            self._make_tables(2 * need)
        for name, values in (("counts", counts), ("efficiency", efficiency),
                             ("spread", spread), ("rho_counts", rho_counts), ("rho", rho)):
            self.tables[name][: len(values)] = values
        self.sampler.known, self.sampler.rates = len(counts), len(rho_counts)
        return self.sampler

    def _blocks(self, kernel, inputs: list, outputs: list, count: int | None = None
                ) -> np.ndarray:
        """`kernel` over the blocks of `count` items (the pixels by default; its arguments:
        inputs, first block, count, outputs), split over the host threads; its block sums
        (self.sums' rows)."""
        count = self.n if count is None else count
        blocks = -(-count // BLOCK)
        args = [*inputs, 0, count, *outputs]
        launch = part_launcher(kernel, args, self.device)
        parts = max(1, min(PARTS_PER_THREAD * self.threads, blocks // MIN_PART_BLOCKS))
        if parts == 1:
            launch(blocks, {})
        else:
            bounds = np.linspace(0, blocks, parts + 1).astype(int)
            run_parts(lambda j: launch(int(bounds[j + 1] - bounds[j]),
                                       {len(inputs): int(bounds[j])}), parts, self.threads)
        return self.block_sums[:blocks]

    def record(self, select: np.ndarray, traced: tuple[np.ndarray, ...], end: int, mid: int,
               quarters: int) -> tuple[np.ndarray, np.ndarray]:
        """A launch's open samples (in all, below mid, below the quarter: per selected
        pixel) added to the counts; the spread sums of the halves and of the quarters."""
        def view(a: np.ndarray) -> wp.array:
            return wp.array(np.ascontiguousarray(a, np.int64), dtype=wp.int64,
                            device=self.device, copy=False)

        sums = self._blocks(record_round, [view(select), *map(view, traced), end, mid,
                                           quarters],
                            [self.done, self.opened, self.before, self.sums], len(select))
        totals = sums.sum(axis=0)
        return totals[:3], totals[3:]

    def errors(self) -> float:
        """Each pixel's estimated squared error into `contribution`; their sum. The Beta
        prior of `posterior_variance` is fitted to the image by moments: its spread is the
        spread of the estimates less their sampling variance."""
        sums = self._blocks(image_sums, [self.done, self.opened, self.sampler], [self.sums])
        mean = float(sums[:, 0].sum()) / self.n
        sampling = float(sums[:, 1].sum()) / self.n
        deviations = self._blocks(deviation_sums, [self.done, self.opened, mean],
                                  [self.sums])
        spread = float(deviations[:, 0].sum()) / self.n - sampling
        prior = 0.0 < mean < 1.0 and spread > 0.0
        a = b = 0.0
        if prior:
            total = max(mean * (1.0 - mean) / spread - 1.0, 1e-6)
            a, b = mean * total, (1.0 - mean) * total
        sums = self._blocks(contributions, [self.done, self.opened, self.sampler, a, b,
                                            int(prior)], [self.contribution, self.sums])
        return float(sums[:, 0].sum())

    def allocation_sums(self, max_spp: int, max_error: float | None
                        ) -> tuple[float, float, float, int]:
        """`want` set to the pixels max_error asks to double; sums of what doubling them
        removes, of the squared errors of pixels with room, of the sigmas; the candidates
        (pixels with room not wanted)."""
        error = -1.0 if max_error is None else float(max_error)
        sums = self._blocks(allocation_sums, [self.done, self.opened, self.contribution,
                                              self.sampler, max_spp, error],
                            [self.want, self.sums])
        drop, room, sigmas, candidates = sums[:, :4].sum(axis=0)
        return float(drop), float(room), float(sigmas), int(candidates)

    def sort_candidates(self, max_spp: int, neyman_scale: float, count: int) -> SortedPrefix:
        """The `count` candidates in allocation order (a stable radix sort of their keys)."""
        if self.keys is None:
            self.keys = wp.empty(2 * self.n, dtype=wp.int32, device=self.device)
            self.order = wp.empty(2 * self.n, dtype=wp.int32, device=self.device)
        self._blocks(allocation_keys, [self.done, self.opened, self.want, self.sampler,
                                       max_spp, neyman_scale, self.powers],
                     [self.keys, self.order])
        wp.utils.radix_sort_pairs(self.keys, self.order, self.n, end_bit=KEY_BITS)
        return SortedPrefix(self, count)

    def mark(self, count: int) -> None:
        """Want the first `count` sorted candidates too."""
        wp.launch(mark, dim=count, inputs=[self.order, self.want], device=self.device)

    def wanted(self) -> np.ndarray:
        return np.flatnonzero(self.want.numpy())


class SortedPrefix:
    """Prefix sums over the sorted candidates of what doubling removes (column 0) and the
    rays it traces (column 1): block sums, then one block's terms when a search lands in
    it."""

    def __init__(self, stats: RoundStatistics, count: int) -> None:
        self.stats, self.count = stats, count
        sums = stats._blocks(sorted_sums, [stats.order, stats.done, stats.contribution,
                                           stats.sampler], [stats.sums], count)
        self.ends = np.cumsum(sums[:, :2], axis=0)  # inclusive, per block
        self.block = -1

    def _inside(self, block: int) -> np.ndarray:
        """Inclusive prefix sums of one block's terms."""
        if block != self.block:
            start = block * BLOCK
            size = min(BLOCK, self.count - start)
            stats = self.stats
            wp.launch(sorted_values, dim=size, inputs=[
                stats.order, stats.done, stats.contribution, stats.sampler, start],
                outputs=[stats.terms], device=stats.device)
            self.prefix = np.cumsum(stats.terms.numpy()[:size], axis=0)
            if block:
                self.prefix += self.ends[block - 1]
            self.block = block
        return self.prefix

    def first(self, column: int, at_least: float) -> int:
        """The first sorted index whose prefix is >= at_least (the last when none is)."""
        block = int(np.searchsorted(self.ends[:, column], at_least, side="left"))
        if block == len(self.ends):
            return self.count - 1
        inside = self._inside(block)[:, column]
        return block * BLOCK + min(int(np.searchsorted(inside, at_least, side="left")),
                                   len(inside) - 1)

    def at(self, column: int, index: int) -> float:
        """The prefix at a sorted index."""
        return float(self._inside(index // BLOCK)[index % BLOCK, column])

    def total(self, column: int) -> float:
        return float(self.ends[-1, column])
