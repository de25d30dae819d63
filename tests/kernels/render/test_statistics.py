"""The adaptive controller's round statistics as Warp kernels (kernels/render/statistics.py)
against the numpy code they replaced (adaptive_reference.py): the same squared errors, the
same allocation and the same bookkeeping on random states, the same bits on any number of
host threads, the allocation keys' arithmetic against float32 bits, and a round that
doubles each selected pixel once."""

from __future__ import annotations

import math

import numpy as np
import pytest
import warp as wp
from scenesort.kernels.render import adaptive, statistics

from tests.kernels.render import adaptive_reference as reference

# (aim, max_pixel_error, max_spp): the allocation's branches (short of the need, the tail,
# every candidate, nothing to do), the per-pixel bound alone and with an aim, full pixels
CASES = [(0.01, None, 4096), (0.03, None, 4096), (0.06, None, 4096), (0.2, None, 4096),
         (None, 0.1, 4096), (0.03, 0.2, 4096), (0.01, 0.1, 32), (0.02, None, 64)]


def state(n: int, seed: int) -> tuple[np.ndarray, ...]:
    """Counts as rounds leave them: 16-128 samples, most pixels open, a few dark, some that
    agree on every sample."""
    rng = np.random.default_rng(seed)
    done = rng.choice([16, 32, 64, 128], n, p=[0.4, 0.3, 0.2, 0.1]).astype(np.int64)
    p = np.where(rng.random(n) < 0.2, 1.0, rng.beta(2.0, 0.7, n))
    opened = rng.binomial(done, p).astype(np.int64)
    before = rng.binomial(done // 2, p).astype(np.int64)
    return done, opened, before


def pair(n: int, seed: int, threads: int | None = None):
    """The same counts and measurements as the kernels' SampleCounts and the reference's."""
    done, opened, before = state(n, seed)
    spread = {16: 0.45, 32: 0.33, 64: 0.27}
    rho = {32: 0.36, 64: 0.41} if seed % 2 else {16: 0.37}
    new = adaptive.SampleCounts(done.copy(), opened.copy(), before.copy(), threads=threads,
                                spread=dict(spread), rho=dict(rho))
    old = reference.SampleCounts(done.copy(), opened.copy(), before.copy(),
                                 spread=dict(spread), rho=dict(rho))
    return new, old


@pytest.mark.parametrize("n", [1, 4095, 4097, 30000])
def test_errors_and_allocation_match_the_numpy_reference(n):
    sizes = set()
    for seed, (aim, bound, max_spp) in enumerate(CASES):
        new, old = pair(n, seed)
        assert math.isclose(new.mse(), old.mse(), rel_tol=1e-12)
        # per pixel the same operations; the image's prior from sums in another order
        np.testing.assert_allclose(new.statistics().contribution.numpy(), old.contribution(),
                                   rtol=1e-11)
        want = reference.next_round(old, aim, bound, max_spp)
        got = adaptive.next_round(new, aim, bound, max_spp)
        np.testing.assert_array_equal(got, want)
        sizes.add(min(len(got), 2) if len(got) < n else "all")
    if n > 1:
        assert sizes == {0, 2, "all"}  # some cases select none, some part, some every pixel


def test_same_bits_on_any_number_of_threads():
    """Sums of fixed blocks in a fixed order: threads change who sums a block, not the sum."""
    n = 200_000  # 49 blocks: several parts on 2 and 3 threads
    results = []
    for threads in (1, 2, 3):
        counts, _ = pair(n, 3, threads)
        mse = counts.mse()
        select = adaptive.next_round(counts, 0.02, 0.2, 4096)
        group = select[counts.done[select] == 16]
        traced = tuple(np.arange(len(group)) * (c + 1) % 17 for c in range(3))
        counts.trace(lambda *_, traced=traced: traced, group, 16)
        results.append((mse, select, counts.sums[32].tobytes(),
                        counts.sums_before[32].tobytes(), counts.mse()))
    for other in results[1:]:
        assert other[0] == results[0][0] and other[2:] == results[0][2:]
        np.testing.assert_array_equal(other[1], results[0][1])


@pytest.mark.parametrize(("first", "count"), [(0, 16), (16, 16), (32, 32), (16, 8)])
def test_record_matches_the_numpy_bookkeeping(first, count):
    """A round's samples added to the counts, and the halves' and quarters' spread pooled,
    as the numpy code did: quarters traced in the launch (0, 16), kept from the round
    before (16, 16 and 32, 32), none (16, 8: the end is 24)."""
    n = 10_000
    new, old = pair(n, 5)
    for counts in (new, old):
        counts.done[:] = first
        counts.open[:] = np.minimum(counts.open, first)
        counts.before[:] = np.minimum(counts.before, first // 2)
    select = np.flatnonzero(np.arange(n) % 3 != 1)
    rng = np.random.default_rng(9)
    opened = rng.binomial(count, 0.6, len(select)).astype(np.int64)
    traced = (opened, opened // 2, opened // 4)
    for counts in (new, old):
        counts.sums[first + count] = np.array([0.5, 1.5, 7.0])  # pooled with earlier rounds
        counts.trace(lambda *_: traced, select, count)
    for name in ("done", "open", "before"):
        np.testing.assert_array_equal(getattr(new, name), getattr(old, name))
    for store in ("sums", "sums_before"):
        mine, theirs = getattr(new, store), getattr(old, store)
        assert mine.keys() == theirs.keys()
        for key in mine:
            np.testing.assert_allclose(mine[key], theirs[key], rtol=1e-12)
    assert new.spread.keys() == old.spread.keys() and new.rho.keys() == old.rho.keys()
    for key in old.spread:
        assert math.isclose(new.spread[key], old.spread[key], rel_tol=1e-12)
    for key in old.rho:
        assert math.isclose(new.rho[key], old.rho[key], rel_tol=1e-12)
    assert (first + count in old.rho) == (first != 16 or count != 8)  # a rate where measured


@wp.kernel
def keys_of(gains: wp.array(dtype=wp.float32), under: wp.array(dtype=wp.int32),
            powers: wp.array(dtype=wp.float64), keys: wp.array(dtype=wp.int32)):
    i = wp.tid()
    keys[i] = statistics.allocation_key(gains[i], under[i] != 0, powers)


def test_allocation_keys_are_the_float32_bits():
    """The kernel's key from arithmetic equals the one from the bits: every exponent,
    1/16-octave boundaries and the floats just below them, subnormals."""
    rng = np.random.default_rng(1)
    edges = np.ldexp(1.0 + np.arange(16)[:, None] / 16.0,
                     np.arange(-126, 128)[None, :]).astype(np.float32).ravel()
    below = np.nextafter(edges, np.float32(0.0))
    subnormal = np.float32(2.0**-149) * rng.integers(1, 2**23, 500).astype(np.float32)
    spread = np.exp(rng.uniform(-85.0, 85.0, 5000)).astype(np.float32)
    gains = np.concatenate([edges, below, subnormal, spread,
                            np.float32([np.finfo(np.float32).max, 2.0**-149])])
    gains = gains[np.isfinite(gains) & (gains > 0)]
    under = rng.random(len(gains)) < 0.5
    out = wp.empty(len(gains), dtype=wp.int32, device="cpu")
    wp.launch(keys_of, dim=len(gains), inputs=[wp.array(gains, dtype=wp.float32, device="cpu"),
                                               wp.array(under.astype(np.int32), device="cpu"),
                                               statistics.powers_of_two()],
              outputs=[out], device="cpu")
    np.testing.assert_array_equal(out.numpy(), reference.allocation_key(gains, under))


def test_a_round_doubles_each_selected_pixel_once(monkeypatch):
    """Pixels selected at different counts in one round each double once, as next_round
    predicted (a group once read the counts after an earlier group had doubled into it,
    and doubled those pixels again)."""
    from scenesort.ao_options import AoOptions  # noqa: PLC0415

    rng = np.random.default_rng(4)
    p = np.where(rng.random(6000) < 0.8, 1.0, rng.beta(0.6, 0.6, 6000))  # dark spots

    def trace_round(select, first, count, mid, quarter):
        opened = rng.binomial(count, p[select])
        return opened, rng.binomial(opened, 0.5), rng.binomial(opened, 0.25)

    rounds = []
    real = adaptive.next_round

    def spy(counts, *args):
        if rounds:
            before, chosen = rounds[-1]
            grown = counts.done - before
            np.testing.assert_array_equal(grown[chosen], before[chosen])
            assert grown.sum() == before[chosen].sum()  # the others unchanged
        select = real(counts, *args)
        rounds.append((counts.done.copy(), select))
        return select

    monkeypatch.setattr(adaptive, "next_round", spy)
    adaptive.sample_rounds(trace_round, len(p), AoOptions(target_error=0.02, max_spp=1024),
                           lambda *_: None)
    assert len(rounds) >= 3
    assert any(len(np.unique(done[chosen])) > 1 for done, chosen in rounds)  # mixed rounds


def test_tables_of_more_counts_than_their_first_capacity():
    """A fixed render measures the spread at the end of every round, so its tables can hold
    more counts than SAMPLER_CAPACITY (they grow): the same errors and allocation as the
    numpy reference with 300 measured counts, pixels between and beyond them."""
    rng = np.random.default_rng(12)
    n = 5000
    done = rng.integers(1, 700, n).astype(np.int64)
    p = rng.beta(2.0, 0.7, n)
    opened = rng.binomial(done, p).astype(np.int64)
    before = rng.binomial(done // 2, p).astype(np.int64)
    known = sorted(rng.choice(np.arange(2, 650), 300, replace=False).tolist())
    spread = {int(k): float(rng.uniform(0.2, 0.6)) for k in known}
    rho = {int(k): float(rng.uniform(0.25, 0.5)) for k in known[::2]}
    assert len(spread) > statistics.SAMPLER_CAPACITY
    new = adaptive.SampleCounts(done.copy(), opened.copy(), before.copy(),
                                spread=dict(spread), rho=dict(rho))
    old = reference.SampleCounts(done.copy(), opened.copy(), before.copy(),
                                 spread=dict(spread), rho=dict(rho))
    assert math.isclose(new.mse(), old.mse(), rel_tol=1e-12)
    np.testing.assert_allclose(new.statistics().contribution.numpy(), old.contribution(),
                               rtol=1e-11)
    for aim, bound, max_spp in CASES:
        np.testing.assert_array_equal(adaptive.next_round(new, aim, bound, max_spp),
                                      reference.next_round(old, aim, bound, max_spp))


def test_a_fixed_render_of_many_rounds_is_the_one_round_render(monkeypatch):
    """A fixed render traces runs of pixels with all their samples (rounds of ROUND_RAYS
    rays): 80 rounds give the one round's image and, to the last bits of a sum, its
    estimate. Regressions: rounds of a few samples of every pixel measured the sampler's
    rate at no count (an estimate 2.7x the one round's here), and more than 64 of them
    overflowed the sampler's tables (the render failed); the quarters of runs too small to
    measure were dropped from the rate (0.5% off)."""
    from benchmarks.scene_kinds import scene_kind  # noqa: PLC0415
    from scenesort import kernels  # noqa: PLC0415

    scene = scene_kind("interior", 64, 48)
    bvh = kernels.build_bvh(scene.vertices, scene.indices)
    o, d, tmin, tmax = scene.camera.rays()
    whole = kernels.render_ao(bvh, o, d, spp=80, tmin=tmin, tmax=tmax)
    assert whole.rays.rounds == 1
    monkeypatch.setattr(adaptive, "ROUND_RAYS", len(o))  # about 38 pixels a round
    rounds = kernels.render_ao(bvh, o, d, spp=80, tmin=tmin, tmax=tmax)
    assert rounds.rays.rounds == 80 > statistics.SAMPLER_CAPACITY
    np.testing.assert_array_equal(rounds.ao, whole.ao)
    assert rounds.rmse_estimate == pytest.approx(whole.rmse_estimate, rel=1e-9)
