"""The adaptive controller: which samples each round of occlusion rays traces, and when
the render stops. Fixed mode (no error target): every hit pixel's `spp` samples, in rounds
of at most ROUND_RAYS rays (a progress call between rounds).

Adaptive sampling, two stopping rules, which may be combined:
- `target_error` is the image's RMSE over hit pixels against the converged AO (the
  expectation of infinitely many samples). The render estimates it as
  sqrt(mean_i efficiency(n_i) * v_i / n_i) over the hit pixels (`rmse_estimate`), v_i
  the pixel's `posterior_variance` (about its sample variance where its samples disagree;
  where they agree, not 0 but what a Beta prior fitted to the image says), and stops
  once that estimate is below RMSE_AIM * target_error. RMSE_AIM leaves room for the
  estimate's own error and for the last round's overshoot, so that the achieved RMSE lies
  in [0.7, 1.0] x target_error in at least 95% of renders (tests/kernels/render/
  test_ao_target.py over seeds; benchmarks/ao_error.py on every shared scene): that is
  the confidence the API states. Samples go where they lower the image's error most per
  ray (Neyman allocation, n_i in proportion to sigma_i): every hit pixel gets the
  minimum spp in one launch (the kernel also counts the open samples among its first
  half and quarter, so that the sampler's rate is measured before the first decision;
  a pixel's rays in one launch share the cache: two launches of half the minimum cost
  1.5x one on blade), then each round doubles the pixels below their Neyman count, those
  with the largest sigma_i^2 / n_i^2 (the variance each new ray removes; in 1/16-octave
  steps, sorted by radix) first, until the
  doubled set is predicted to remove DROP_SHORT of what is left above the aim (all of
  it when at most SHORT_NEED aim^2 a pixel is left; TAIL_MARGIN aim^2 a pixel past it,
  with at least MIN_ROUND of the rays so far, when that round would trace less than
  TAIL_ROUND of them; every pixel when it would take FULL_ROUND of the rays left, unless
  even the fastest Sobol rate could then take it below FULL_ROUND_AIM of the aim: a
  round's fixed cost is worth more than a small overshoot); sigma_i^2 is the
  Jeffreys-smoothed variance below, so that a pixel whose few samples agreed still earns
  more.
- `max_pixel_error` bounds every pixel (a per-pixel rule; target_error bounds the image):
  pixels whose 95% half-width z * sqrt(spread * s^2 / n) is still >= it double their
  samples (`half_width`; spread as below).
A pixel's samples are always a power-of-two prefix of its Sobol sequence (when the
minimum is one), up to `max_spp`. In the half-width and the allocation s^2 is the
sample variance, and where all n samples agreed p(1-p) at the Jeffreys posterior mean
p = (k + 1/2) / (n + 1) instead of 0, so a pixel is not declared exact on the strength
of a few samples that missed a small occluder. Owen-scrambled Sobol samples have less
variance than independent ones. `spread` is measured at every sample count n a round
reaches, on the pixels whose samples disagree, from each pixel's estimate after n/2
against after n samples (`sampler_efficiency`; independent samples: ~1). For Sobol the
halves are anti-correlated, so the spread overstates the variance where it falls faster
than 1/n: `efficiency` corrects it by the rate measured on the same pixels (see
`SampleCounts.efficiency_at`). A count without a measurement takes the nearest smaller one's
(efficiency falls as n grows, so this is never optimistic).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from scenesort.ao_options import AoOptions

Z95 = 1.959963984540054  # two-sided 95% normal quantile
RMSE_AIM = 0.82  # target_error: stop at this fraction of it (the estimate's margin)
# Owen-scrambled Sobol on an integrand with discontinuities (an occluder's edge) in 2D:
# variance O(n^(-1 - 1/d)) = n^-1.5 (He and Wang 2015), so doubling keeps >= 2^-1.5 of it
RHO_MIN = 2.0**-1.5
DROP_SHORT = 0.8  # target_error: a round aims at this fraction of the MSE still to go,
SHORT_NEED = 1.0  # when that is over this many aim^2 (per pixel); else at all of it
FULL_ROUND = 0.5  # target_error: a round with this fraction of the rays left doubles all,
FULL_ROUND_AIM = 0.9  # if that is predicted to stay above this fraction of the aim
TAIL_ROUND = 0.125  # target_error: a round under this fraction of the rays so far aims at all
TAIL_MARGIN = 0.05  # target_error: a tail round aims this many aim^2 below the aim
MIN_ROUND = 1.0 / 32.0  # target_error: fewest rays in a round, as a fraction of those so far
EFFICIENCY_MIN = 0.05  # never trust a sampler to beat independent samples by more than 20x
EFFICIENCY_PIXELS = 64  # disagreeing pixels needed to measure the efficiency in a round
ROUND_RAYS = 1 << 21  # occlusion rays per round (between progress calls) in fixed mode

# (selected hit pixels, first sample, samples per pixel, mid, quarter) -> per selected pixel:
# its open samples, and those among them with index below mid and below quarter
RoundTracer = Callable[[np.ndarray, int, int, int, int], tuple[np.ndarray, ...]]
Progress = Callable[[float, str], None]


def sample_rounds(trace_round: RoundTracer, pixels: int, opts: AoOptions,
                  report: Progress, counts: SampleCounts | None = None,
                  ) -> tuple[SampleCounts, int]:
    """Trace the occlusion samples of `pixels` hit pixels round by round until `opts` is
    met; the counts and the number of rounds. `report(fraction, "occlusion")` is called
    before each round. `counts`: every pixel's first `opts.min_spp` samples, traced
    already (`SampleCounts.trace` in one call: the filtered film's, whose first samples
    find the covered pixels); the rounds go on from there."""
    rounds = 0
    min_spp = opts.min_spp
    if counts is not None:
        if not opts.adaptive or not pixels:
            return counts, rounds
        aim = None if opts.target_error is None else RMSE_AIM * opts.target_error
        return counts, _adaptive_rounds(trace_round, counts, opts, report, aim,
                                        counts.mse(), next_round(counts, aim,
                                                                 opts.max_pixel_error,
                                                                 opts.max_spp))
    counts = SampleCounts(*(np.zeros(pixels, dtype=np.int64) for _ in range(3)))
    if not opts.adaptive:
        count = max(1, min(min_spp, ROUND_RAYS // max(pixels, 1)))
        everyone = np.arange(pixels)
        while pixels and count > 0:
            report(float(counts.done.sum()) / (min_spp * pixels), "occlusion")
            counts.trace(trace_round, everyone, count)
            rounds += 1
            count = min(count, min_spp - int(counts.done[0]))
        return counts, rounds
    aim = None if opts.target_error is None else RMSE_AIM * opts.target_error
    return counts, _adaptive_rounds(trace_round, counts, opts, report, aim, None,
                                    np.arange(pixels))


def _adaptive_rounds(trace_round: RoundTracer, counts: SampleCounts, opts: AoOptions,
                     report: Progress, aim: float | None, mse0: float | None,
                     select: np.ndarray) -> int:
    """sample_rounds' adaptive rounds from `select` on (`mse0`: the MSE after the first
    round, None before it); the number of rounds traced."""
    rounds = 0
    while len(counts.done) and len(select):
        if aim is not None and mse0 is not None:
            report(error_progress(mse0, counts.mse(), aim), "occlusion")
        else:
            report(samples_progress(counts.done, len(select), int(counts.done[select[0]])),
                   "occlusion")
        for n in np.unique(counts.done[select]):  # one launch set per sample count
            # doubling: Sobol prefixes of 2^k; the minimum's nested estimates (after a
            # quarter and a half of it) measure how fast the variance falls before the
            # first decision
            counts.trace(trace_round, select[counts.done[select] == n], int(n) or opts.min_spp)
        rounds += 1
        mse0 = counts.mse() if mse0 is None else mse0
        select = next_round(counts, aim, opts.max_pixel_error, opts.max_spp)
    return rounds


def nested_marks(first: int, count: int) -> tuple[int, int]:
    """The sample indices below which a launch of samples first..first+count-1 counts its
    nested estimates (`RoundTracer`'s mid and quarter): about half and a quarter of the
    samples at its end; -1: none."""
    end = first + count
    return max(end // 2, first), end // 4 if end % 4 == 0 else -1


@dataclass
class SampleCounts:
    """Per hit pixel: samples traced and open; per sample count n reached by doubling, the
    `sampler_efficiency` of the halves (n/2 against n, `spread`) where enough pixels
    disagreed, and how fast the variance fell on those pixels (`rho`)."""

    done: np.ndarray
    open: np.ndarray
    before: np.ndarray  # open among the first half of each pixel's samples
    spread: dict[int, float] = field(default_factory=dict)
    rho: dict[int, float] = field(default_factory=dict)
    # per count: the pooled sums of every round that reached it (rounds of one count are
    # pooled, so a small late group does not overwrite what thousands of pixels measured)
    sums: dict[int, np.ndarray] = field(default_factory=dict)
    sums_before: dict[int, np.ndarray] = field(default_factory=dict)
    cached: np.ndarray | None = None  # `contribution` since the last `changed()`

    def trace(self, trace_round: RoundTracer, select: np.ndarray, count: int) -> None:
        """Samples n..n+count-1 of the `select`ed pixels, which all have n samples."""
        first = int(self.done[select[0]])
        end = first + count
        # the nested estimates, after about end / 2 and end / 4 samples: counted in the
        # launch where they reach into it, else those kept from the rounds before
        mid, quarter = nested_marks(first, count)
        opened, opened_mid, opened_quarter = trace_round(select, first, count, mid, quarter)
        open_now = self.open[select]
        open_mid = open_now + opened_mid
        open_quarter = (open_now + opened_quarter if quarter >= first
                        else self.before[select] if 2 * quarter == first == count else None)
        self.measure(end, mid, open_mid, open_now + opened, open_quarter)
        self.before[select] = open_mid
        self.open[select] = open_now + opened
        self.done[select] += count
        self.changed()

    def measure(self, n: int, mid: int, open_mid: np.ndarray, open_end: np.ndarray,
                open_before: np.ndarray | None) -> None:
        """Pool one round's nested estimates (mid against n samples; before: mid/2
        against mid) at count n."""
        def pooled(store: dict, key: int, *args: np.ndarray) -> np.ndarray:
            store[key] = store.get(key, 0.0) + _spread_sums(*args)
            return store[key]

        total = pooled(self.sums, n, open_mid, mid, open_end, n)
        if total[2] < EFFICIENCY_PIXELS:
            return
        self.spread[n] = float(np.clip(total[0] / total[1], EFFICIENCY_MIN, 1.0))
        if open_before is not None:  # the same pixels' previous halves: the rate
            before = pooled(self.sums_before, n, open_before, mid // 2, open_mid, mid)
            if before[2] >= EFFICIENCY_PIXELS:
                ratio = (total[0] / total[1]) / (2.0 * before[0] / before[1])
                self.rho[n] = min(max(ratio, RHO_MIN), 0.5)

    def efficiency_at(self, n: np.ndarray) -> np.ndarray:
        """The sampler's efficiency (variance over the independent samples' p(1-p)/n) at
        each count n. The halves' spread overstates it where the variance falls faster than
        1/n (Owen-scrambled Sobol: the halves are anti-correlated): with
        rho = Var(n)/Var(n/2) it is spread * rho / (1 - rho) (spread itself when rho = 1/2,
        independent samples). rho is spread(n) / (2 spread(n/2)) on the pixels that
        doubled to n, in [RHO_MIN, 1/2]; at the first count, that of the next; 1/2 (the
        pessimistic end) when unmeasured. A count without a measurement takes the nearest
        smaller one's (efficiency falls as n grows, so this never flatters); 1.0 below
        every one."""
        return self._at(n, lambda m: self.spread[m] * self._rho(m) / (1.0 - self._rho(m)))

    def spread_at(self, n: np.ndarray) -> np.ndarray:
        """The halves' spread itself at each count (what max_pixel_error has always used:
        not corrected for rho, so a pixel bound never rests on a rate estimate)."""
        return self._at(n, lambda m: self.spread[m])

    def _at(self, n: np.ndarray, value: Callable[[int], float]) -> np.ndarray:
        known = sorted(self.spread)
        values = np.array([1.0] + [value(m) for m in known])
        return values[np.searchsorted(np.array(known, dtype=np.int64), n, side="right")]

    def _rho(self, m: int) -> float:
        return self.rho.get(m, self.rho.get(2 * m, 0.5))

    def rho_at(self, n: np.ndarray) -> np.ndarray:
        """Var(2n) / Var(n) expected for each count n: the latest measured rho at or
        below 2n (1/2 when none)."""
        known = sorted(self.rho)
        values = np.array([0.5] + [self.rho[m] for m in known])
        return values[np.searchsorted(np.array(known, dtype=np.int64), 2 * n, side="right")]

    def contribution(self) -> np.ndarray:
        """Each hit pixel's estimated squared error, efficiency * s^2 / n (kept until the
        next `changed()`: the progress report, the allocation and the result ask for it
        between two rounds, each a pass over every hit pixel)."""
        if self.cached is None:
            eff = self.efficiency_at(self.done)
            self.cached = eff * posterior_variance(self.open, self.done, eff) / self.done
        return self.cached

    def changed(self) -> None:
        """The counts changed (a round was traced): forget `contribution`."""
        self.cached = None

    def mse(self) -> float:
        """Estimated mean squared error over hit pixels, mean of `contribution`."""
        return float(np.mean(self.contribution()))


def next_round(counts: SampleCounts, aim: float | None, max_pixel_error: float | None,
                max_spp: int) -> np.ndarray:
    """The hit pixels whose samples the next round doubles (empty: done).

    max_pixel_error: every pixel whose half-width is not yet below it. aim (the RMSE to
    reach): while the estimate is above it, the pixels below their Neyman count
    n*_i = sigma_i sum_j sigma_j / (H aim^2) by more than a factor sqrt(2), those with the
    most variance removed per ray first, as many as the estimate predicts it needs (then,
    if those are not enough, the others in the same order)."""
    n, k = counts.done, counts.open
    eff = counts.efficiency_at(n)
    room = n < max_spp
    want = np.zeros(len(n), dtype=bool)
    if max_pixel_error is not None:
        want |= room & (half_width(k, n, counts.spread_at(n)) >= max_pixel_error)
    if aim is not None:
        contribution = counts.contribution()
        # doubling keeps rho(n) of a pixel's variance (1/2 for independent samples)
        drop = contribution * (1.0 - counts.rho_at(n))
        need = (contribution.mean() - aim**2) * len(n) - drop[want].sum()
        if need > 0.0 and np.any(room & ~want):
            sigma = np.sqrt(eff * smoothed_variance(k, n))
            neyman = sigma * sigma.sum() / (len(n) * aim**2)
            order = np.flatnonzero(room & ~want)
            gain = (sigma[order] / n[order]).astype(np.float32) ** 2  # removed per ray
            order = order[np.argsort(allocation_key(gain, neyman[order] > math.sqrt(2.0)
                                                     * n[order]), kind="stable")]
            dropped = np.cumsum(drop[order])
            rays = np.cumsum(n[order])  # doubling a pixel traces as many rays as it has
            # a round with much to go stops short of the aim (DROP_SHORT of the need):
            # Sobol's variance often falls faster than the last measured rho says, and an
            # overshoot cannot be undone, while a shortfall costs one more round. With at
            # most SHORT_NEED aim^2 to go it aims at all of it: selected pixels' drops came
            # out up to 1.25x the prediction (measured on the shared scenes),
            # which lands at >= 0.75 aim^2, inside the calibration band ((0.7 / 0.82)^2 =
            # 0.73), and the shortfall round it saves has a fixed cost (launches, this
            # allocation over every hit pixel; sponza at 0.05 went from 5 rounds to 3,
            # 1.25x to 1.17x the time of the fixed render of its RMSE). A round that
            # would be small (under TAIL_ROUND of the rays so far) aims TAIL_MARGIN aim^2
            # past the need (an exact prediction falls short half the time, and each
            # shortfall is one more tail: sponza at 0.05 had two) and traces at least
            # MIN_ROUND of the rays so far
            short = DROP_SHORT if need > SHORT_NEED * aim**2 * len(n) else 1.0
            end = _first(dropped >= short * need)
            so_far = float(n.sum())
            if rays[end] < TAIL_ROUND * so_far:
                end = max(_first(dropped >= need + TAIL_MARGIN * aim**2 * len(n)),
                          _first(rays >= MIN_ROUND * so_far))
            want[order[: end + 1]] = True
            # a round that would double most of the image doubles all of it (the pixels
            # left out would be the next round's, with its own fixed cost), unless that
            # could land below FULL_ROUND_AIM of the aim (the calibration band) if the
            # variance fell as fast as Sobol's can (RHO_MIN), not as fast as measured
            fastest = contribution.sum() - (1.0 - RHO_MIN) * contribution[room].sum()
            if (rays[end] >= FULL_ROUND * rays[-1]
                    and fastest >= (FULL_ROUND_AIM * aim) ** 2 * len(n)):
                want[order] = True
    return np.flatnonzero(want)


def allocation_key(gain: np.ndarray, under: np.ndarray) -> np.ndarray:
    """Sort keys (int16, which numpy's stable sort orders by radix) for doublings: those
    `under` the Neyman count first, then by the variance removed per ray, `gain` (positive
    float32), in steps of 1/16 octave (ties in the given order)."""
    # a positive float32's bits grow with it: sign 0, then 8 exponent bits, then mantissa
    octave16 = gain.view(np.int32) >> 19  # 12 bits: exponent and the mantissa's first 4
    return (np.int16(4095) - octave16.astype(np.int16)
            + np.where(under, 0, 4096).astype(np.int16))


def _first(condition: np.ndarray) -> int:
    """Index of the first True (the last index when there is none)."""
    return int(np.argmax(condition)) if condition.any() else len(condition) - 1


def sampler_efficiency(open_mid: np.ndarray, n_mid: np.ndarray, open_end: np.ndarray,
                       n_end: np.ndarray, default: float = 1.0) -> float:
    """The sampler's variance relative to independent samples, pooled over pixels.

    For nested estimates m_mid (first n_mid samples) and m_end (all n_end), independent
    samples give E[(m_mid - m_end)^2] = Var(m_end) (n_end - n_mid) / n_mid; a stratified
    (Sobol) sequence gives less. The ratio of the summed squared differences to the summed
    Bernoulli variances p(1-p)(n_end - n_mid)/(n_mid n_end) estimates Var(sampler) /
    Var(independent) at this sample count. Only pixels whose samples disagree take part
    (fully open or occluded ones would pull it toward 0). Clipped to [EFFICIENCY_MIN, 1];
    `default` when too few pixels disagree to tell."""
    diff2, bernoulli, mixed = _spread_sums(open_mid, n_mid, open_end, n_end)
    if mixed < EFFICIENCY_PIXELS:
        return float(default)
    return float(np.clip(diff2 / bernoulli, EFFICIENCY_MIN, 1.0))


def _spread_sums(open_mid: np.ndarray, n_mid: np.ndarray | int, open_end: np.ndarray,
                 n_end: np.ndarray | int) -> np.ndarray:
    """`sampler_efficiency`'s sums over the disagreeing pixels: (squared differences,
    Bernoulli variances, pixels), so that measurements of one count can be pooled. The
    counts are per pixel or one for all (a round's: no array of copies)."""
    mixed = np.flatnonzero((open_end > 0) & (open_end < n_end) & (n_mid > 0)
                           & (n_end > n_mid))
    if not len(mixed):
        return np.zeros(3)

    def take(x: np.ndarray | int) -> np.ndarray | float:
        return x[mixed].astype(np.float64) if np.ndim(x) else float(x)

    n_mid, n_end = take(n_mid), take(n_end)
    p = open_end[mixed] / n_end
    diff2 = (open_mid[mixed] / n_mid - p) ** 2
    bernoulli = p * (1.0 - p) * ((n_end - n_mid) / (n_mid * n_end))
    return np.array([diff2.sum(), np.sum(bernoulli), float(len(mixed))])


def sample_variance(open_count: np.ndarray, n: np.ndarray) -> np.ndarray:
    """The unbiased sample variance of each pixel's n 0/1 samples (0 where they agree)."""
    n = n.astype(np.float64)
    p = open_count / n
    return p * (1.0 - p) * n / np.maximum(n - 1.0, 1.0)


def posterior_variance(open_count: np.ndarray, n: np.ndarray, efficiency: np.ndarray
                       ) -> np.ndarray:
    """E[p(1-p) | k of n open] per pixel under a Beta(a, b) prior on the pixels' p fitted
    to the image by moments (empirical Bayes): about the sample variance where samples
    disagree, and not 0 where they agree, by as much as the image says pixels like it
    vary. The prior's spread is the spread of the estimates less their sampling
    variance (efficiency * s^2 / n)."""
    k = open_count.astype(np.float64)
    n = n.astype(np.float64)
    p = k / n
    mean = float(p.mean())
    spread = float(p.var() - np.mean(efficiency * sample_variance(open_count, n) / n))
    if not (0.0 < mean < 1.0) or spread <= 0.0:
        return sample_variance(open_count, n)
    total = max(mean * (1.0 - mean) / spread - 1.0, 1e-6)
    a, b = mean * total, (1.0 - mean) * total
    return (a + k) * (b + n - k) / ((a + b + n) * (a + b + n + 1.0))


def smoothed_variance(open_count: np.ndarray, n: np.ndarray) -> np.ndarray:
    """`sample_variance`, but where all n samples agreed p(1-p) at the Jeffreys posterior
    mean p = (k + 1/2) / (n + 1) (Brown, Cai and DasGupta 2001), about 1/(2n): an occluder
    smaller than ~1/n of the hemisphere is still possible."""
    q = (open_count + 0.5) / (n + 1.0)
    agree = (open_count == 0) | (open_count == n)
    return np.where(agree, q * (1.0 - q), sample_variance(open_count, n))


def half_width(open_count: np.ndarray, n: np.ndarray, efficiency: float | np.ndarray
               ) -> np.ndarray:
    """95% half-width of each pixel's estimate, z * sqrt(efficiency * s^2 / n), with the
    `smoothed_variance` (never 0). `efficiency` (<= 1, one or per pixel) is the sampler's
    variance relative to independent samples (`sampler_efficiency`)."""
    return Z95 * np.sqrt(efficiency * smoothed_variance(open_count, n) / n)


def error_progress(mse0: float, mse: float, aim: float) -> float:
    """How far the error has come from mse0 towards aim^2, on a log scale, in [0, 1]. In
    logs apart: for a tiny target aim^2 underflows to 0."""
    if not (mse > aim * aim and mse0 > mse > 0.0):
        return 1.0 if mse <= aim * aim else 0.0
    span = math.log(mse0) - 2.0 * math.log(aim)
    return min(1.0, (math.log(mse0) - math.log(mse)) / span)


def samples_progress(n_done, active, count) -> float:
    """Progress with max_pixel_error: samples done over samples planned (planned grows, so
    this is an estimate, never above 1)."""
    done = float(n_done.sum())
    planned = done + float(active * count)
    return min(done / planned, 1.0) if planned > 0 else 0.0
