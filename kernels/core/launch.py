"""Host-side launch helpers: the device, host threads, numpy views, launches in parts.

A Warp CPU launch is one serial loop on one thread (WARP_FACTS.md), so on CPU independent
work is split between host threads that launch side by side (the launch releases the
Python lock): in parts with arguments of their own (`part_launcher`, `run_parts`), or as
chunks claimed from one call's counter (core.claim); on CUDA one launch covers everything.
The host threads are one persistent pool for the whole process (`host_pool`): starting
threads for every call cost about 0.5 ms per thread. Claimed launches use helper threads
that wait natively instead (core.helpers), and this pool where those are busy.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import warp as wp

PARTS_PER_THREAD = 8  # parts per host thread of a launch in parts, for load balance


def get_device(device) -> wp.context.Device:
    """Warp's device for `device` (None: Warp's default), initialising Warp first."""
    wp.init()
    return wp.get_device(device)


def load_modules(device, *modules) -> float:
    """Load these Warp modules on the device, compiling those the kernel cache lacks;
    returns the milliseconds it took. Called before a call's clock starts, so that Warp's
    compile time (seconds on first use) is reported apart from the work's."""
    start = time.perf_counter()
    for module in modules:
        wp.load_module(module, device=device)
    return (time.perf_counter() - start) * 1e3


def sync_ms(device, start: float) -> float:
    """Milliseconds since `start` (a perf_counter reading) once the device is idle."""
    wp.synchronize_device(device)
    return (time.perf_counter() - start) * 1e3


def cpu_cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()


def host_threads(device, threads: int | None) -> int:
    """Host threads that split a launch: every core on CPU unless told; one on CUDA."""
    if not device.is_cpu:
        return 1
    return cpu_cores() if threads is None else max(1, int(threads))


def to_device(a: np.ndarray, dtype, device) -> wp.array:
    """A Warp view of a contiguous numpy array on CPU (no copy), a copy elsewhere."""
    return wp.array(a, dtype=dtype, device=device, copy=not device.is_cpu)


def launch_key(kernel, device, args: list) -> tuple:
    """What a recorded launch of `kernel` is specific to: which arguments are numpy arrays
    (core.claim), and for a generic kernel, whose overload follows its arguments' kinds,
    their dtypes too (which struct, which dtype)."""
    if not kernel.is_generic:  # its types fixed: 2 us less a small call (trace's 11)
        return (kernel, device.alias, tuple(map(type, args)))
    return (kernel, device.alias, tuple((type(x), getattr(x, "dtype", None),
                                         getattr(x, "ndim", None)) for x in args))


_recorded = threading.local()  # per host thread: {(kernel, device, argument kinds): Launch}


def part_launcher(kernel, args: list, device) -> Callable[[int, dict[int, Any]], None]:
    """launch(dim, changes): `kernel` over dim items with its arguments `args` (inputs,
    then outputs), argument i replaced by changes[i] (every call names the same i), from
    any host thread. wp.launch resolves a generic kernel's overload and packs every
    argument each time (on CPU, 47 us a launch of the AO kernel against 5 us re-launching a
    recorded one, measured; 62 us to record the trace kernel against 14 us to set all its
    arguments in a recorded one), and a split launch makes PARTS_PER_THREAD of them per
    thread: so each thread records a kernel's launch once per process and after that only
    sets the arguments, all of them at its first launch of a call, then what changed."""
    key = launch_key(kernel, device, args)
    call = object()  # which call's arguments a thread's launch holds

    def launch(dim: int, changes: dict[int, Any]) -> None:
        kept = _recorded.__dict__.get(key)
        if kept is None:
            values = [changes.get(i, x) for i, x in enumerate(args)]
            cmd = wp.launch(kernel, dim=dim, inputs=values, device=device, record_cmd=True)
            # kept between calls: it must not keep this call's arrays alive (its packed
            # parameters are plain pointers, set anew before it runs again)
            cmd.fwd_args = cmd.adj_args = None
            kept = _recorded.__dict__[key] = [cmd, call]
        elif kept[1] is not call:
            for i, x in enumerate(args):
                kept[0].set_param_at_index(i, changes.get(i, x))
            kept[1] = call
        else:
            for i, x in changes.items():
                kept[0].set_param_at_index(i, x)
        kept[0].set_dim(dim)
        kept[0].launch()

    return launch


_pool: ThreadPoolExecutor | None = None
_pool_size = 0
_pool_lock = threading.Lock()


def host_pool(threads: int) -> ThreadPoolExecutor:
    """The process's persistent host threads, at least `threads` of them (and one per core):
    made on first use, grown (replaced) when a caller needs more at once."""
    global _pool, _pool_size
    with _pool_lock:
        if _pool is None or _pool_size < threads:
            # The old pool is not shut down: a caller may still be submitting to it; its
            # idle threads cost nothing (and growing is rare: more workers than cores).
            _pool_size = max(threads, cpu_cores())
            _pool = ThreadPoolExecutor(_pool_size, thread_name_prefix="kernels-host")
        return _pool


def _forget_pool() -> None:  # a forked child has the parent's pool object, not its threads
    global _pool, _pool_size
    _pool, _pool_size = None, 0


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def run_parts(fn: Callable[[int], None], parts: int, threads: int) -> None:
    """fn(0) .. fn(parts - 1) on `threads` threads, the caller and persistent host threads,
    each taking the next part when it is done with one (as `ThreadPoolExecutor(threads).map`
    would); the first exception is raised here, once every thread has stopped."""
    if threads <= 1 or parts <= 1:
        for k in range(parts):
            fn(k)
        return
    next_part = iter(range(parts))
    lock = threading.Lock()

    def runner() -> None:
        while True:
            with lock:
                k = next(next_part, None)
            if k is None:
                return
            fn(k)

    # The caller runs parts too: waking a pool thread and waking the caller again at the end
    # cost ~0.1 ms each, a tenth of a 10k-ray call's work.
    helpers = [host_pool(threads - 1).submit(runner) for _ in range(min(threads, parts) - 1)]
    try:
        runner()
    finally:
        # a helper not yet awake when the parts ran out is not waited for (~0.1 ms)
        helpers = [f for f in helpers if not f.cancel()]
        for f in helpers:
            f.exception()  # wait: the parts write into the caller's arrays
    for f in helpers:
        f.result()
