"""The adaptive controller's statistics in numpy, as they were before they became Warp
kernels (kernels/render/statistics.py): the independent reference the kernels are tested
against, bit for bit where the arithmetic is per pixel, to rounding where it sums."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scenesort.kernels.render.adaptive import (
    DROP_SHORT,
    EFFICIENCY_MIN,
    EFFICIENCY_PIXELS,
    FULL_ROUND,
    FULL_ROUND_AIM,
    MIN_ROUND,
    RHO_MIN,
    SHORT_NEED,
    TAIL_MARGIN,
    TAIL_ROUND,
    RoundTracer,
    nested_marks,
)
from scenesort.kernels.render.statistics import Z95_VALUE as Z95


@dataclass
class SampleCounts:
    """Per hit pixel: samples traced and open, the spread and rate measured per count."""

    done: np.ndarray
    open: np.ndarray
    before: np.ndarray
    spread: dict[int, float] = field(default_factory=dict)
    rho: dict[int, float] = field(default_factory=dict)
    sums: dict[int, np.ndarray] = field(default_factory=dict)
    sums_before: dict[int, np.ndarray] = field(default_factory=dict)

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

    def measure(self, n: int, mid: int, open_mid: np.ndarray, open_end: np.ndarray,
                open_before: np.ndarray | None) -> None:
        """Pool one round's nested estimates (mid against n samples; before: mid/2
        against mid) at count n."""
        def pooled(store: dict, key: int, *args: np.ndarray) -> np.ndarray:
            store[key] = store.get(key, 0.0) + _spread_sums(*args)
            return store[key]

        total = pooled(self.sums, n, open_mid, mid, open_end, n)
        before = (None if open_before is None else
                  pooled(self.sums_before, n, open_before, mid // 2, open_mid, mid))
        if total[2] < EFFICIENCY_PIXELS:
            return
        self.spread[n] = float(np.clip(total[0] / total[1], EFFICIENCY_MIN, 1.0))
        if before is not None and before[2] >= EFFICIENCY_PIXELS:  # the previous halves
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
        eff = self.efficiency_at(self.done)
        return eff * posterior_variance(self.open, self.done, eff) / self.done

    def mse(self) -> float:
        return float(np.mean(self.contribution()))


def next_round(counts: SampleCounts, aim: float | None, max_pixel_error: float | None,
                max_spp: int) -> np.ndarray:
    """adaptive.next_round in numpy (its docstring and comments say why)."""
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
            short = DROP_SHORT if need > SHORT_NEED * aim**2 * len(n) else 1.0
            end = _first(dropped >= short * need)
            so_far = float(n.sum())
            if rays[end] < TAIL_ROUND * so_far:
                end = max(_first(dropped >= need + TAIL_MARGIN * aim**2 * len(n)),
                          _first(rays >= MIN_ROUND * so_far))
            want[order[: end + 1]] = True
            fastest = contribution.sum() - (1.0 - RHO_MIN) * contribution[room].sum()
            if (rays[end] >= FULL_ROUND * rays[-1]
                    and fastest >= (FULL_ROUND_AIM * aim) ** 2 * len(n)):
                want[order] = True
    return np.flatnonzero(want)


def _first(condition: np.ndarray) -> int:
    """Index of the first True (the last index when there is none)."""
    return int(np.argmax(condition)) if condition.any() else len(condition) - 1


def allocation_key(gain: np.ndarray, under: np.ndarray) -> np.ndarray:
    """Sort keys (int16, which numpy's stable sort orders by radix) for doublings: those
    `under` the Neyman count first, then by the variance removed per ray, `gain` (positive
    float32), in steps of 1/16 octave (ties in the given order)."""
    # a positive float32's bits grow with it: sign 0, then 8 exponent bits, then mantissa
    octave16 = gain.view(np.int32) >> 19  # 12 bits: exponent and the mantissa's first 4
    return (np.int16(4095) - octave16.astype(np.int16)
            + np.where(under, 0, 4096).astype(np.int16))


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
