"""Host launch helpers: one persistent pool of host threads for every split launch."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import warp as wp
from scenesort.kernels.core import launch
from scenesort.kernels.core.launch import host_pool, launch_split, load_modules, run_parts

from scenesort import kernels

from ..reference import random_rays, random_soup

pytestmark = pytest.mark.host_only  # host threads: CPU launches


def test_split_launches_reuse_the_same_host_threads():
    """Many traces start no thread after the first (a new pool per launch cost ~0.5 ms a
    thread), and give the one-thread answer."""
    rng = np.random.default_rng(0)
    v, f = random_soup(rng, 500)
    o, d = random_rays(rng, 40_000, -0.5, 1.5)
    bvh = kernels.build_bvh(v, f, device="cpu")
    one = kernels.trace(bvh, o, d, threads=1)
    kernels.trace(bvh, o, d, threads=2)
    pool = host_pool(2)
    before = threading.active_count()
    for _ in range(20):
        two = kernels.trace(bvh, o, d, threads=2)
    assert threading.active_count() == before
    assert host_pool(2) is pool
    assert np.array_equal(one.t, two.t) and np.array_equal(one.triangle, two.triangle)


def test_run_parts_keeps_to_the_thread_count_and_raises():
    """However big the pool, `threads` parts at most run at once; every part runs once; an
    exception in a part reaches the caller."""
    host_pool(8)  # a pool bigger than asked for below
    lock = threading.Lock()
    running, most, done = [0], [0], []

    def part(k: int) -> None:
        with lock:
            running[0] += 1
            most[0] = max(most[0], running[0])
        time.sleep(0.002)
        with lock:
            running[0] -= 1
            done.append(k)

    run_parts(part, 40, 3)
    assert sorted(done) == list(range(40)) and most[0] <= 3

    def fail(k: int) -> None:
        if k == 5:
            raise RuntimeError("part 5")

    with pytest.raises(RuntimeError, match="part 5"):
        run_parts(fail, 10, 2)


def test_launch_split_outputs_equal_one_launch():
    """Per-item arrays are sliced per part, shorter ones passed whole."""
    n = 50_000
    out_one = wp.zeros(n, dtype=float, device="cpu")
    out_split = wp.zeros(n, dtype=float, device="cpu")
    x = wp.array(np.arange(n, dtype=np.float32), dtype=float, device="cpu")
    scale = wp.array(np.array([2.0], np.float32), dtype=float, device="cpu")
    launch_split(_scaled, n, [scale], [x], [], [out_one], wp.get_device("cpu"), 1)
    launch_split(_scaled, n, [scale], [x], [], [out_split], wp.get_device("cpu"), 4)
    assert np.array_equal(out_one.numpy(), out_split.numpy())
    assert out_split.numpy()[-1] == 2.0 * (n - 1)


@wp.kernel
def _scaled(scale: wp.array(dtype=float), x: wp.array(dtype=float),
            out: wp.array(dtype=float)):
    i = wp.tid()
    out[i] = scale[0] * x[i]


def test_load_modules_reports_milliseconds():
    ms = load_modules(wp.get_device("cpu"), _scaled.module)
    assert ms >= 0.0 and load_modules(wp.get_device("cpu")) < 1.0


def test_a_forked_child_starts_its_own_pool(monkeypatch):
    host_pool(2)
    launch._forget_pool()  # what the at-fork hook runs in a child
    assert launch._pool is None and host_pool(2) is not None
