"""The pool's clock: a tick counter every worker can read, and its rate.

`ticks()` reads a counter that runs at a constant rate and that user code may read on
every target:
  CUDA     `clock64()`: the multiprocessor's cycles (a worker stays on one multiprocessor,
           so the differences it takes are consistent);
  x86-64   `rdtsc`: the time-stamp counter, which counts at a constant rate on every CPU
           Warp runs on (invariant TSC) and is synchronised between cores;
  AArch64  `cntvct_el0`: the generic timer's virtual count, readable at EL0 on Linux, macOS
           and Windows (24 MHz on Apple silicon, 1 GHz on Armv8.6 and later).
           (`__builtin_readcyclecounter()` reads `pmccntr_el0` there, which user code may
           not read: the macOS arm64 zip ships this code.)
  other    a logical clock: one tick per read by any worker, shared by all of them (a
           relaxed atomic add). Defining SCENESORT_PORTABLE_CLOCK compiles it on any target,
           so that tests run it.

The rate differs by target and machine (from 24 MHz to a few GHz), so nothing counts in
ticks: the per-phase time shares of a pool launch are ratios of ticks, and the one bound
in time, how long an idle worker waits before the pool is declared stuck, is stated in
seconds (pool.state.WAIT_SECONDS) and converted with `ticks_per_second`, measured once per
device and process: a one-thread launch reads the counter in a loop for MEASURE_SECONDS
of host time (for the logical clock this measures reads per second, so the bound counts
idle polls: at least WAIT_SECONDS / workers of them when all workers poll at once).
"""

from __future__ import annotations

import functools
import time

import warp as wp

from ..core.compile_options import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)

MEASURE_SECONDS = 0.01  # host time the rate is measured over (a GPU clocks up meanwhile)


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    return clock64();
#elif (defined(__x86_64__) || defined(_M_X64)) && !defined(SCENESORT_PORTABLE_CLOCK)
    return (int64_t)__builtin_ia32_rdtsc();
#elif (defined(__aarch64__) || defined(_M_ARM64)) && !defined(SCENESORT_PORTABLE_CLOCK)
    int64_t count;
    __asm__ __volatile__("mrs %0, cntvct_el0" : "=r"(count));
    return count;
#else
    static int64_t reads = 0;
    return __atomic_add_fetch(&reads, 1, __ATOMIC_RELAXED);
#endif
"""
)
def ticks() -> wp.int64:
    """The device's tick counter (module docstring): differences taken by one worker are
    elapsed ticks; `ticks_per_second` converts them."""
    ...


@wp.kernel(enable_backward=False)
def spin_clock(reads: int, out: wp.array(dtype=wp.int64)):
    """Read the clock `reads` times in a row; out = (first reading, last reading)."""
    first = ticks()
    last = first
    for _ in range(reads):
        last = ticks()
    out[0] = first
    out[1] = last


def measure_ticks_per_second(device, kernel: wp.Kernel = spin_clock) -> float:
    """Ticks per second of the clock compiled into `kernel` (a `spin_clock` of some module)
    on `device`: the readings of one launch that spins for MEASURE_SECONDS of host time
    at least, over that time (launch overhead included: a slight underestimate)."""
    device = wp.get_device(device)
    out = wp.zeros(2, dtype=wp.int64, device=device)
    wp.load_module(kernel.module, device=device)
    reads = 1 << 10
    while True:
        wp.synchronize_device(device)
        start = time.perf_counter()
        wp.launch(kernel, dim=1, inputs=[reads, out], device=device)
        wp.synchronize_device(device)
        seconds = time.perf_counter() - start
        if seconds >= MEASURE_SECONDS or reads >= 1 << 30:
            break
        reads *= 4
    first, last = (int(x) for x in out.numpy())
    return max(last - first, 1) / seconds


@functools.cache
def _ticks_per_second(alias: str) -> float:
    return measure_ticks_per_second(alias)


def ticks_per_second(device) -> float:
    """The rate of `ticks()` on this device, measured once per process."""
    return _ticks_per_second(wp.get_device(device).alias)


WARP_MODULES = (spin_clock.module,)  # this module's kernels (see core.launch.load_modules)
