"""Host launch helpers: one persistent pool of host threads for every split launch."""

from __future__ import annotations

import gc
import threading
import time
import weakref
from typing import Any

import numpy as np
import pytest
import warp as wp
from scenesort.kernels.core import launch
from scenesort.kernels.core.claim import MIN_CLAIM, Claims, claimed_items, launch_claimed
from scenesort.kernels.core.launch import (
    host_pool,
    load_modules,
    part_launcher,
    run_parts,
)

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


def test_the_caller_runs_parts_and_an_error_waits_for_the_others():
    """The calling thread takes parts too (waking a pool thread costs ~0.1 ms); when its
    part raises, run_parts returns only once the other threads' parts have stopped (they
    write into the caller's arrays)."""
    host_pool(2)
    ran_on, finished = set(), []

    def part(k: int) -> None:
        ran_on.add(threading.get_ident())
        time.sleep(0.005)

    run_parts(part, 8, 2)
    assert threading.get_ident() in ran_on and len(ran_on) == 2

    helper_started = threading.Event()

    def caller_fails(k: int) -> None:
        if threading.get_ident() == caller:
            assert helper_started.wait(5)
            raise RuntimeError("the caller's part")
        helper_started.set()
        time.sleep(0.05)
        finished.append(k)

    caller = threading.get_ident()
    with pytest.raises(RuntimeError, match="the caller's part"):
        run_parts(caller_fails, 2, 2)
    assert len(finished) == 1  # the helper's part ended before the error came back


def test_a_helper_not_yet_started_is_not_waited_for():
    """When the caller has run every part before a helper woke, run_parts returns at once:
    here every pool thread is busy, so no helper can start."""
    pool = host_pool(2)
    release = threading.Event()
    busy = [pool.submit(release.wait, 10) for _ in range(launch._pool_size)]
    try:
        ran = []
        start = time.perf_counter()
        run_parts(ran.append, 4, 2)
        assert sorted(ran) == [0, 1, 2, 3] and time.perf_counter() - start < 5
    finally:
        release.set()
        for f in busy:
            f.result()


@wp.struct
class _Add:
    value: float


@wp.struct
class _Times:
    value: float


@wp.func
def _apply(op: _Add, x: float) -> float:
    return x + op.value


@wp.func
def _apply(op: _Times, x: float) -> float:  # noqa: F811
    return x * op.value


@wp.kernel
def _applied(op: Any, x: wp.array(dtype=float), out: wp.array(dtype=float)):
    i = wp.tid()
    out[i] = _apply(op, x[i])


def _overload_cases(n: int) -> list:
    """(op, expected) for x = arange(n): a struct, another struct (another overload of a
    generic kernel), the first again."""
    add, times = _Add(), _Times()
    add.value, times.value = 10.0, 3.0
    return [(add, np.arange(n) + 10.0), (times, np.arange(n) * 3.0),
            (add, np.arange(n) + 10.0)]


def test_recorded_launches_follow_each_calls_arguments_and_keep_none_alive():
    """A thread's recorded launch is reused by later calls: with another overload of a
    generic kernel (another struct) it is another launch, every call's arrays are its own
    (also when two calls' parts alternate on one thread), and no array outlives its call
    through the kept launch."""
    device = wp.get_device("cpu")
    x = wp.array(np.arange(6, dtype=np.float32), dtype=float, device=device)
    cases = _overload_cases(6)
    add = cases[0][0]
    for op, expected in cases:
        out = wp.zeros(6, dtype=float, device=device)
        part_launcher(_applied, [op, x, out], device)(6, {})
        assert np.array_equal(out.numpy(), expected)
    out = wp.zeros(6, dtype=float, device=device)
    gone = weakref.ref(out)
    launch = part_launcher(_applied, [add, x, out], device)
    launch(3, {})
    launch(3, {1: x[3:], 2: out[3:]})  # a second part of the same call: only what changed
    assert np.array_equal(out.numpy(), np.arange(6) + 10.0)
    del launch, out
    gc.collect()
    assert gone() is None
    # two calls' parts interleaved on one thread (calls from two requests share the pool)
    outs = [wp.zeros(6, dtype=float, device=device) for _ in range(2)]
    other = _Add()
    other.value = -1.0
    first, second = (part_launcher(_applied, [op, x, o], device)
                     for op, o in zip((add, other), outs, strict=True))
    first(3, {})
    second(6, {})
    first(3, {1: x[3:], 2: outs[0][3:]})
    assert np.array_equal(outs[0].numpy(), np.arange(6) + 10.0)
    assert np.array_equal(outs[1].numpy(), np.arange(6) - 1.0)


@wp.kernel
def _scaled(scale: wp.array(dtype=float), x: wp.array(dtype=float),
            out: wp.array(dtype=float)):
    i = wp.tid()
    out[i] = scale[0] * x[i]


@wp.kernel
def _claimed(x: wp.array(dtype=wp.vec3), out: wp.array(dtype=float),
             first: wp.array(dtype=int), claims: Claims):
    items = claimed_items(claims, wp.tid())
    for i in range(items[0], items[1]):
        out[i] = out[i] + x[i][1]  # twice would show
        first[i] = items[0]


@pytest.mark.parametrize("threads", [1, 2, 4])
@pytest.mark.parametrize("align", [1, 64])
def test_claimed_chunks_cover_every_item_once(threads, align):
    """Every item in exactly one chunk, each chunk starting at a multiple of `align` and
    no longer than the call needs; numpy arrays (read-only too, as a request body's) and
    Warp arrays alike as arguments."""
    device = wp.get_device("cpu")
    for n in (1, 63, 64, 65, 1000, 100_003):
        x = np.zeros((n, 3), np.float32)
        x[:, 1] = np.arange(1, n + 1)
        x.flags.writeable = n % 2 == 0
        out = np.zeros(n, np.float32)
        first = wp.full(n, -1, dtype=int, device=device)
        launch_claimed(_claimed, n, [x, out, first], device, threads, align)
        assert np.array_equal(out, x[:, 1])
        starts = first.numpy()
        assert (starts % align == 0).all() and (starts <= np.arange(n)).all()
        chunk = np.arange(n) - starts
        if threads > 1 and n > MIN_CLAIM * threads:
            assert len(np.unique(starts)) > threads  # chunks, not one part a thread
        assert chunk.max() < max(n // threads + align, MIN_CLAIM + align)


def test_claimed_calls_from_two_threads_keep_their_own_arguments():
    """Calls at once from two Python threads (a service's requests) each get their own
    recorded launch."""
    device = wp.get_device("cpu")
    n = 50_000
    results = {}

    def call(k: int) -> None:
        for _ in range(20):
            x = np.full((n, 3), float(k), np.float32)
            out = np.zeros(n, np.float32)
            launch_claimed(_claimed, n, [x, out, wp.empty(n, dtype=int, device=device)],
                           device, 2)
            results.setdefault(k, []).append(bool((out == k).all()))

    threads = [threading.Thread(target=call, args=(k,)) for k in (1, 2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert results == {1: [True] * 20, 2: [True] * 20}


@wp.kernel
def _claimed_applied(op: Any, x: wp.array(dtype=float), out: wp.array(dtype=float),
                     claims: Claims):
    items = claimed_items(claims, wp.tid())
    for i in range(items[0], items[1]):
        out[i] = _apply(op, x[i])


def test_claimed_launches_follow_each_calls_arguments_and_keep_none_alive():
    """A kept recorded launch serves later calls: another overload of a generic kernel
    (another struct) is another launch, every call's arrays are its own, and no array
    outlives its call through the kept launch."""
    device = wp.get_device("cpu")
    x = wp.array(np.arange(300, dtype=np.float32), dtype=float, device=device)
    cases = _overload_cases(300)
    add = cases[0][0]
    for op, expected in cases:
        for threads in (1, 2):
            out = wp.zeros(300, dtype=float, device=device)
            launch_claimed(_claimed_applied, 300, [op, x, out], device, threads)
            assert np.array_equal(out.numpy(), expected)
    out = wp.zeros(300, dtype=float, device=device)
    gone = weakref.ref(out)
    launch_claimed(_claimed_applied, 300, [add, x, out], device, 2)
    del out
    gc.collect()
    assert gone() is None


def test_a_claimed_launch_refuses_a_numpy_array_of_the_wrong_kind():
    device = wp.get_device("cpu")
    first = wp.empty(4, dtype=int, device=device)
    for x in (np.zeros(12, np.float32), np.zeros((4, 3), np.float64),
              np.zeros((3, 4), np.float32)[:, :3]):
        with pytest.raises(TypeError, match="parameter x: a contiguous float32 array of "
                                            "12-byte rows"):
            launch_claimed(_claimed, 4, [x, np.zeros(4, np.float32), first], device, 1)


def test_load_modules_reports_milliseconds():
    ms = load_modules(wp.get_device("cpu"), _scaled.module)
    assert ms >= 0.0 and load_modules(wp.get_device("cpu")) < 1.0


def test_a_forked_child_starts_its_own_pool(monkeypatch):
    host_pool(2)
    launch._forget_pool()  # what the at-fork hook runs in a child
    assert launch._pool is None and host_pool(2) is not None
