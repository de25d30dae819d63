"""Host-side launch helpers: the device, host threads, numpy views, split launches.

A Warp CPU launch is one serial loop on one thread (WARP_FACTS.md), so on CPU independent
work is split into parts that host threads launch side by side (the launch releases the
Python lock); on CUDA one launch covers everything.
"""

from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import warp as wp

PARTS_PER_THREAD = 8  # launch_split: parts per host thread, for load balance
MIN_PART = 4096  # launch_split: fewest items worth a launch of their own


def get_device(device) -> wp.context.Device:
    """Warp's device for `device` (None: Warp's default), initialising Warp first."""
    wp.init()
    return wp.get_device(device)


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


def launch_split(kernel, n: int, shared: list, per_item: list, scalars: list, outputs: list,
                 device, threads: int) -> None:
    """Launch `kernel` over n items, split into contiguous parts run by `threads` host
    threads (only on CPU, where a launch is serial). Arrays in `per_item` and `outputs`
    of length n are sliced per part; shorter ones (a broadcast scalar) are passed whole."""
    if n == 0:
        return
    # More parts than threads, taken in turn by the pool's threads: camera rays cost very
    # different amounts in different parts of the image (sky against geometry).
    parts = min(threads * PARTS_PER_THREAD, max(1, n // MIN_PART)) if threads > 1 else 1
    if parts <= 1:
        wp.launch(kernel, dim=n, inputs=[*shared, *per_item, *scalars], outputs=outputs,
                  device=device)
        return
    wp.load_module(kernel.module, device=device)  # compile once, not in every thread
    bounds = np.linspace(0, n, parts + 1).astype(int)

    def part(x: wp.array, a: int, b: int) -> wp.array:
        return x[a:b] if x.shape[0] == n else x

    def run(k: int) -> None:
        a, b = int(bounds[k]), int(bounds[k + 1])
        wp.launch(kernel, dim=b - a, inputs=[*shared, *(part(x, a, b) for x in per_item),
                                             *scalars],
                  outputs=[part(x, a, b) for x in outputs], device=device)

    with ThreadPoolExecutor(threads) as ex:
        list(ex.map(run, range(parts)))
