"""The pool's clock (pool.clock): a rate measured per device, the idle bound in seconds
whatever that rate (24 MHz on Apple silicon, GHz elsewhere), and the logical clock of
targets without a counter user code may read, compiled here on purpose."""

from __future__ import annotations

import time

import pytest
import warp as wp
from scenesort.kernels.core.compile_options import MODULE_OPTIONS
from scenesort.kernels.pool.clock import measure_ticks_per_second, spin_clock, ticks_per_second
from scenesort.kernels.pool.state import PoolError, check_pool, make_pool

from .test_pool import toy_setup, toy_worker


def test_the_rate_is_a_clocks(device):
    """From the 24 MHz generic timer of Apple silicon to a few GHz (TSC, SM clock)."""
    assert 1e6 <= ticks_per_second(device) <= 1e11


def stuck_pool_seconds(worker, device, wait_seconds=None, max_idle=None) -> float:
    """Seconds until one of two workers gives up on a pool whose last task waits for a
    dependency that never finishes (the error checked)."""
    pool = make_pool(8, workers=2, min_chunks=4, device=device, wait_seconds=wait_seconds)
    if max_idle is not None:
        pool.max_idle = max_idle
    order = wp.zeros(1, dtype=int, device=device)
    log = wp.zeros(32, dtype=int, device=device)
    wp.launch(toy_setup, dim=1, inputs=[pool, 5, 2], device=device)
    wp.synchronize_device(device)
    start = time.perf_counter()
    wp.launch(worker, dim=1, inputs=[pool, 5, order, log], device=device)
    wp.synchronize_device(device)
    seconds = time.perf_counter() - start
    with pytest.raises(PoolError, match="stuck with 1 unfinished tasks"):
        check_pool(pool)
    return seconds


def test_an_idle_worker_waits_the_bound_in_seconds(device):
    """WAIT_SECONDS and `wait_seconds` are seconds on every device: converted with the
    measured rate, 0.2 s is neither microseconds nor hours of waiting."""
    assert 0.1 <= stuck_pool_seconds(toy_worker, device, wait_seconds=0.2) < 30.0


@pytest.mark.host_only
def test_the_portable_clock_keeps_the_pool_working():
    """SCENESORT_PORTABLE_CLOCK compiles the logical clock (one tick per read) on this CPU:
    it advances by exactly the reads, its rate is measured as a counter's, and an idle
    worker's bound converted with it still ends a stuck pool."""
    module = f"{__name__}.portable"
    spin = wp.kernel(spin_clock.func, module=module)
    worker = wp.kernel(toy_worker.func, module=module)
    flags = (wp.config.cpu_compiler_flags or "") + " -DSCENESORT_PORTABLE_CLOCK"
    wp.set_module_options({**MODULE_OPTIONS, "cpu_compiler_flags": flags}, module=module)
    out = wp.zeros(2, dtype=wp.int64)
    wp.launch(spin, dim=1, inputs=[1000, out])
    first, last = out.numpy()
    assert last - first == 1000
    rate = measure_ticks_per_second("cpu", spin)
    assert rate > 0
    assert stuck_pool_seconds(worker, "cpu", wait_seconds=0.0, max_idle=int(0.05 * rate)) < 30.0
