"""The adaptive controller: which samples each round of occlusion rays traces, and when
the render stops. Fixed mode (no error target): every hit pixel's `spp` samples, in rounds
of at most ROUND_RAYS rays (a progress call between rounds); adaptive rounds, too, in runs
of at most ROUND_RAYS rays, a progress call before each.

Adaptive sampling, two stopping rules, which may be combined:
- `target_error` is the image's RMSE over hit pixels against the converged AO (the
  expectation of infinitely many samples). The render estimates it as
  sqrt(mean_i efficiency(n_i) * v_i / n_i) over the hit pixels (`rmse_estimate`), v_i
  the pixel's posterior variance (statistics.py; about its sample variance where its
  samples disagree; where they agree, not 0 but what a Beta prior fitted to the image
  says), and stops
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
  steps, Warp's radix sort) first, until the
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
  samples (statistics.allocation_sums; spread as below).
A pixel's samples are always a power-of-two prefix of its Sobol sequence (when the
minimum is one), up to `max_spp`. In the half-width and the allocation s^2 is the
sample variance, and where all n samples agreed p(1-p) at the Jeffreys posterior mean
p = (k + 1/2) / (n + 1) instead of 0, so a pixel is not declared exact on the strength
of a few samples that missed a small occluder. Owen-scrambled Sobol samples have less
variance than independent ones. `spread` is measured at every sample count n a round
reaches, on the pixels whose samples disagree, from each pixel's estimate after n/2
against after n samples (statistics.spread_terms; independent samples: ~1). For Sobol the
halves are anti-correlated, so the spread overstates the variance where it falls faster
than 1/n: `efficiency` corrects it by the rate measured on the same pixels (see
`SampleCounts.sampler`). A count without a measurement takes the nearest smaller one's
(efficiency falls as n grows, so this is never optimistic).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from scenesort.ao_options import AoOptions

from .statistics import (
    QUARTERS_KEPT,
    QUARTERS_NONE,
    QUARTERS_TRACED,
    RoundStatistics,
    Sampler,
)

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
ROUND_RAYS = 1 << 21  # occlusion rays per run between progress calls (a fixed round)

# (selected hit pixels, first sample, samples per pixel, mid, quarter) -> per selected pixel:
# its open samples, and those among them with index below mid and below quarter
RoundTracer = Callable[[np.ndarray, int, int, int, int], tuple[np.ndarray, ...]]
Progress = Callable[[float, str], None]


def sample_rounds(trace_round: RoundTracer, pixels: int, opts: AoOptions,
                  report: Progress, counts: SampleCounts | None = None,
                  ) -> tuple[SampleCounts, int]:
    """Trace the occlusion samples of `pixels` hit pixels round by round until `opts` is
    met; the counts and the number of rounds. `report(fraction, "occlusion")` is called
    before each run of at most about ROUND_RAYS rays (where a caller's Esc stops it).
    `counts`: every pixel's first `opts.min_spp` samples, traced already
    (`SampleCounts.trace` in one call: the filtered film's, whose first samples find the
    covered pixels); the rounds go on from there."""
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
    counts = SampleCounts(*(np.zeros(pixels, dtype=np.int64) for _ in range(3)),
                          threads=opts.threads)
    if not opts.adaptive:
        # runs of pixels with all their samples each: every pixel's nested estimates (at a
        # half and a quarter of its samples) come from one launch, as in a single round, so
        # the estimate does not depend on how many rounds the image takes (rounds of a few
        # samples of every pixel measured the rate at no count: a pessimistic estimate)
        bounds = round_bounds(pixels, min_spp)
        for a, b in zip(bounds[:-1], bounds[1:], strict=True):
            report(float(a) / pixels, "occlusion")
            counts.trace(trace_round, np.arange(a, b), min_spp)
            rounds += 1
        return counts, rounds
    aim = None if opts.target_error is None else RMSE_AIM * opts.target_error
    return counts, _adaptive_rounds(trace_round, counts, opts, report, aim, None,
                                    np.arange(pixels))


def round_bounds(pixels: int, samples: int) -> np.ndarray:
    """Cuts of `pixels` into runs of about ROUND_RAYS rays at `samples` each (at least one
    pixel a run): the rounds of a fixed render, between which progress is reported."""
    runs = max(1, min(pixels, pixels * samples // ROUND_RAYS)) if pixels else 0
    return np.linspace(0, pixels, runs + 1).astype(int)


def _adaptive_rounds(trace_round: RoundTracer, counts: SampleCounts, opts: AoOptions,
                     report: Progress, aim: float | None, mse0: float | None,
                     select: np.ndarray) -> int:
    """sample_rounds' adaptive rounds from `select` on (`mse0`: the MSE after the first
    round, None before it); the number of rounds traced."""
    rounds = 0
    while len(counts.done) and len(select):
        if aim is not None and mse0 is not None:
            fraction = error_progress(mse0, counts.mse(), aim)
        else:
            fraction = samples_progress(counts.done, len(select), int(counts.done[select[0]]))
        # one launch set per sample count, each pixel doubled once as next_round
        # predicted: the groups come from the counts at selection (read after an earlier
        # group of the round had doubled into a later one's count, they would double it
        # again)
        levels = counts.done[select]
        for n in np.flatnonzero(np.bincount(levels)):
            # doubling: Sobol prefixes of 2^k; the minimum's nested estimates (after a
            # quarter and a half of it) measure how fast the variance falls before the
            # first decision
            group, count = select[levels == n], int(n) or opts.min_spp
            # in runs of about ROUND_RAYS rays, each after a progress call (where Esc is
            # seen): a first round of 2M pixels at 16 samples is 32M rays, seconds long;
            # a count's sums are pooled over its runs as over its rounds
            bounds = round_bounds(len(group), count)
            for a, b in zip(bounds[:-1], bounds[1:], strict=True):
                report(fraction, "occlusion")
                counts.trace(trace_round, group[a:b], count)
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
    sampler's efficiency from the halves (n/2 against n, `spread`) where enough pixels
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
    threads: int | None = None  # host threads of the statistics (every core by default)
    cached: float | None = None  # `error_sum` since the last `changed()`
    tables: Sampler | None = None  # `sampler` since the last `changed()`
    stats: RoundStatistics | None = None

    def trace(self, trace_round: RoundTracer, select: np.ndarray, count: int) -> None:
        """Samples n..n+count-1 of the `select`ed pixels, which all have n samples."""
        first = int(self.done[select[0]])
        end = first + count
        # the nested estimates, after about end / 2 and end / 4 samples: counted in the
        # launch where they reach into it, else those kept from the rounds before
        mid, quarter = nested_marks(first, count)
        traced = trace_round(select, first, count, mid, quarter)
        quarters = (QUARTERS_TRACED if quarter >= first
                    else QUARTERS_KEPT if 2 * quarter == first == count else QUARTERS_NONE)
        halves, quarters_sums = self.statistics().record(select, traced, end, mid, quarters)
        self.measure(end, halves, quarters_sums if quarters != QUARTERS_NONE else None)
        self.changed()

    def measure(self, n: int, halves: np.ndarray, quarters: np.ndarray | None) -> None:
        """Pool one round's spread sums (statistics.spread_terms: squared differences,
        Bernoulli variances, pixels) at count n: of the halves (mid against n samples)
        and of the quarters (mid/2 against mid)."""
        def pooled(store: dict, key: int, sums: np.ndarray) -> np.ndarray:
            store[key] = store.get(key, 0.0) + sums
            return store[key]

        total = pooled(self.sums, n, halves)
        # the quarters pooled with the halves, also while too few pixels disagree to measure
        # (a fixed render's first runs of pixels): else the rate would rest on fewer pixels
        before = None if quarters is None else pooled(self.sums_before, n, quarters)
        if total[2] < EFFICIENCY_PIXELS:
            return
        self.spread[n] = float(np.clip(total[0] / total[1], EFFICIENCY_MIN, 1.0))
        if before is not None and before[2] >= EFFICIENCY_PIXELS:  # the same pixels'
            ratio = (total[0] / total[1]) / (2.0 * before[0] / before[1])  # previous halves
            self.rho[n] = min(max(ratio, RHO_MIN), 0.5)

    def sampler(self) -> Sampler:
        """The sampler's measurements (kept until the next `changed()`)."""
        if self.tables is None:
            self.tables = self._tables()
        return self.tables

    def _tables(self) -> Sampler:
        """The sampler's measurements as step functions of a pixel's count n (Warp's).

        Efficiency (variance over the independent samples' p(1-p)/n): the halves' spread
        overstates it where the variance falls faster than 1/n (Owen-scrambled Sobol: the
        halves are anti-correlated): with rho = Var(n)/Var(n/2) it is
        spread * rho / (1 - rho) (spread itself when rho = 1/2, independent samples). rho
        is spread(n) / (2 spread(n/2)) on the pixels that doubled to n, in [RHO_MIN, 1/2];
        at the first count, that of the next; 1/2 (the pessimistic end) when unmeasured. A
        count without a measurement takes the nearest smaller one's (efficiency falls as n
        grows, so this never flatters); 1.0 below every one. The spread itself serves
        max_pixel_error (not corrected for rho, so a pixel bound never rests on a rate
        estimate). The rate table is read at 2n: Var(2n) / Var(n), the latest measured rho
        at or below 2n (1/2 when none)."""
        known, rates = sorted(self.spread), sorted(self.rho)
        return self.statistics().measured(
            known, [1.0] + [self.spread[m] * self._rho(m) / (1.0 - self._rho(m))
                            for m in known],
            [1.0] + [self.spread[m] for m in known], rates,
            [0.5] + [self.rho[m] for m in rates])

    def _rho(self, m: int) -> float:
        return self.rho.get(m, self.rho.get(2 * m, 0.5))

    def statistics(self) -> RoundStatistics:
        """The round statistics' passes over these counts (made once, kept)."""
        if self.stats is None:
            self.stats = RoundStatistics(self.done, self.open, self.before, self.threads)
        return self.stats

    def error_sum(self) -> float:
        """The hit pixels' estimated squared errors, efficiency * s^2 / n each (the
        posterior variance for s^2), summed; computed once per round (the progress report,
        the allocation and the result ask for it between two rounds)."""
        if self.cached is None:
            self.sampler()  # the statistics' step functions, filled for this round
            self.cached = self.statistics().errors()
        return self.cached

    def mse(self) -> float:
        """Estimated mean squared error over hit pixels."""
        return self.error_sum() / len(self.done)

    def changed(self) -> None:
        """The counts changed (a round was traced): forget `error_sum` and `sampler`."""
        self.cached = self.tables = None


def next_round(counts: SampleCounts, aim: float | None, max_pixel_error: float | None,
                max_spp: int) -> np.ndarray:
    """The hit pixels whose samples the next round doubles (empty: done).

    max_pixel_error: every pixel whose half-width is not yet below it. aim (the RMSE to
    reach): while the estimate is above it, the pixels below their Neyman count
    n*_i = sigma_i sum_j sigma_j / (H aim^2) by more than a factor sqrt(2), those with the
    most variance removed per ray first, as many as the estimate predicts it needs (then,
    if those are not enough, the others in the same order). The passes over the pixels are
    Warp kernels (statistics.py); this is the policy between them."""
    stats, pixels = counts.statistics(), len(counts.done)
    mse = counts.mse()  # the pixels' squared errors, in stats.contribution
    # doubling keeps rho(n) of a pixel's variance (1/2 for independent samples)
    drop_wanted, room_error, sigmas, candidates = stats.allocation_sums(
        max_spp, max_pixel_error)
    if aim is not None:
        need = (mse - aim**2) * pixels - drop_wanted
        if need > 0.0 and candidates:
            prefix = stats.sort_candidates(max_spp, sigmas / (pixels * aim**2), candidates)
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
            short = DROP_SHORT if need > SHORT_NEED * aim**2 * pixels else 1.0
            end = prefix.first(0, short * need)
            so_far = float(counts.done.sum())
            if prefix.at(1, end) < TAIL_ROUND * so_far:
                end = max(prefix.first(0, need + TAIL_MARGIN * aim**2 * pixels),
                          prefix.first(1, MIN_ROUND * so_far))
            # a round that would double most of the image doubles all of it (the pixels
            # left out would be the next round's, with its own fixed cost), unless that
            # could land below FULL_ROUND_AIM of the aim (the calibration band) if the
            # variance fell as fast as Sobol's can (RHO_MIN), not as fast as measured
            fastest = counts.error_sum() - (1.0 - RHO_MIN) * room_error
            if (prefix.at(1, end) >= FULL_ROUND * prefix.total(1)
                    and fastest >= (FULL_ROUND_AIM * aim) ** 2 * pixels):
                end = candidates - 1
            stats.mark(end + 1)
    return stats.wanted()


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
