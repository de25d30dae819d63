"""Helper threads that wait for a call's work natively (kernels/core/helpers.py)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time

import pytest
import warp as wp
from scenesort.kernels.core import helpers
from scenesort.kernels.core.atomics import shared_add

pytestmark = [
    pytest.mark.host_only,
    pytest.mark.skipif(helpers.helpers() is None, reason="one core, or not x86-64"),
]


@wp.kernel
def _rendezvous(calls: wp.array(dtype=wp.int32), wanted: int, limit: int):
    # each run counts itself, then waits (boundedly) for `wanted` runs in all
    shared_add(calls, 0, 1)
    i = int(0)
    while shared_add(calls, 0, 0) < wanted and i < limit:
        i += 1


def _until(predicate, seconds: float = 5.0) -> bool:
    end = time.monotonic() + seconds
    while not predicate():
        if time.monotonic() > end:
            return False
        time.sleep(1e-3)
    return True


def _state(pool, r: int) -> int:
    return int(pool.state[r * helpers.ROW])


@pytest.fixture
def pool():
    """A pool of one helper of its own that spins for a second (long enough to find it
    spinning on a loaded machine)."""
    pool = helpers._Helpers(1, spin_seconds=1.0)
    yield pool
    pool.stop()
    assert not pool.threads[0].is_alive()


def test_a_helper_runs_the_callers_entry_asleep_or_spinning(pool):
    """A call finds its helper asleep (woken through Python) or still spinning after the
    last call (posted natively): either way the helper runs the same entry beside the
    caller."""
    calls = wp.zeros(1, dtype=wp.int32, device="cpu")
    entry = helpers._entry_of(_rendezvous, [calls, 2, 200_000_000])
    count = calls.numpy()
    assert _state(pool, 0) == helpers.ASLEEP
    pool.run(entry, pool.take(1))  # run gives its helpers back
    assert count[0] == 2  # the caller's run and the woken helper's
    assert _state(pool, 0) == helpers.SPINNING
    pool.posts[0]()  # a job posted natively, to the spinning helper alone
    assert pool.found[0] == helpers.SPINNING
    assert _until(lambda: count[0] == 3)
    pool.waits[0]()
    assert pool.found[0] == helpers.SPINNING  # done, spinning again
    count[0] = 0
    pool.run(entry, pool.take(1))
    assert count[0] == 2


def test_an_idle_helper_sleeps():
    """After SPIN_SECONDS without a job a helper goes back to sleep: its thread then uses
    no CPU time."""
    pool = helpers.helpers()
    calls = wp.zeros(1, dtype=wp.int32, device="cpu")
    entry = helpers._entry_of(_rendezvous, [calls, 1 + pool.count, 200_000_000])
    pool.run(entry, pool.take(pool.count))
    assert calls.numpy()[0] == 1 + pool.count
    assert _until(lambda: all(_state(pool, r) == helpers.ASLEEP for r in range(pool.count)))
    clocks = [time.pthread_getcpuclockid(t.ident) for t in pool.threads]
    before = [time.clock_gettime(c) for c in clocks]
    time.sleep(0.1)
    assert all(time.clock_gettime(c) - b < 0.005 for c, b in zip(clocks, before, strict=True))


def test_a_job_no_helper_took_is_taken_back(pool):
    """A short entry the caller finishes before a sleeping helper wakes is taken back,
    not waited for; the helper still serves the next call."""
    pool.stop()  # a pool that sleeps at once after each job
    pool = helpers._Helpers(1, spin_seconds=0.0)
    try:
        calls = wp.zeros(1, dtype=wp.int32, device="cpu")
        count = calls.numpy()
        alone = helpers._entry_of(_rendezvous, [calls, 1, 0])
        for _ in range(20):
            assert _until(lambda: _state(pool, 0) == helpers.ASLEEP)
            pool.run(alone, pool.take(1))
            assert _state(pool, 0) in (helpers.SPINNING, helpers.ASLEEP)
        assert 20 <= count[0] <= 40
        count[0] = 0
        both = helpers._entry_of(_rendezvous, [calls, 2, 200_000_000])
        pool.run(both, pool.take(1))
        assert count[0] == 2
    finally:
        pool.stop()


def test_a_call_takes_every_helper_or_none():
    pool = helpers.helpers()
    taken = pool.take(pool.count)
    try:
        assert taken is not None and pool.take(1) is None  # all owned by this caller
    finally:
        pool.give_back(taken)
    assert pool.take(pool.count + 1) is None  # more than there are
    again = pool.take(pool.count)
    assert again is not None
    pool.give_back(again)


@pytest.mark.parametrize("idle", [0.0, 0.2])
def test_a_process_exits_with_its_helpers_spinning_or_asleep(idle):
    """Warp's code must not run while Python exits: the helpers are stopped first. On the
    way, the hits of calls shared with the helper asleep, then spinning, are one thread's."""
    code = textwrap.dedent(f"""
        import time
        import numpy as np
        from scenesort import kernels
        rng = np.random.default_rng(1)
        v = rng.random((3000, 3), dtype=np.float32)
        f = rng.integers(0, 3000, (1000, 3)).astype(np.int32)
        bvh = kernels.build_bvh(v, f)
        o = rng.random((20000, 3), dtype=np.float32)
        d = rng.normal(size=(20000, 3)).astype(np.float32)
        for any_hit in (False, True):
            one = kernels.trace(bvh, o, d, tmax=0.3, any_hit=any_hit, threads=1)
            for _ in range(3):
                two = kernels.trace(bvh, o, d, tmax=0.3, any_hit=any_hit, threads=2)
                assert np.array_equal(one.triangle, two.triangle)
                assert np.array_equal(one.t, two.t)
        time.sleep({idle})
        print("done")
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().endswith("done")


def test_an_entry_keeps_its_modules_code_loaded():
    """Warp unloads a module's code once nothing holds its executable (a load of the same
    module on another thread replaces it: a service's warm-up beside its first job): an
    Entry holds it, so a call after that still runs (it jumped to unmapped memory)."""
    code = textwrap.dedent("""
        import gc
        import warp as wp
        from scenesort.kernels.core import helpers
        out = wp.zeros(1, dtype=wp.int64, device="cpu")
        entry = helpers._entry_of(helpers.clock_kernel, [out])
        helpers.clock_kernel.module.unload()
        gc.collect()
        entry()
        print("ran", int(out.numpy()[0] > 0))
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, (out.returncode, out.stderr[-2000:])
    assert out.stdout.strip().endswith("ran 1")


def test_a_forked_child_makes_its_own_helpers():
    pool = helpers.helpers()
    helpers._forget()  # what the at-fork hook runs in a child
    try:
        assert helpers._helpers is None
    finally:
        helpers._helpers = pool
