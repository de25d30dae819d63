"""The task pool on its own (a toy application) and through the BVH build."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from scenesort.kernels.pool.state import (
    Pool,
    PoolError,
    check_pool,
    make_pool,
    pool_acquire,
    pool_alloc,
    pool_finish,
    pool_idle,
    pool_publish,
    pool_release,
    pool_resolve,
    pool_running,
    pool_wait,
)

from scenesort import kernels

from ..reference import random_soup


@wp.kernel
def toy_worker(pool: Pool, chunks_b: int, order: wp.array(dtype=int), log: wp.array(dtype=int)):
    """Slot 0: task A; slot 1: task B, dependent on A. Each processed chunk appends
    (slot, chunk) to the log; the last finisher of A activates B, of B releases it."""
    idle_since = wp.int64(-1)
    while pool_running(pool):
        got = pool_acquire(pool)
        if got[0] < 0:
            idle_since = pool_idle(pool, idle_since)
            continue
        idle_since = wp.int64(-1)
        for c in range(got[1], got[1] + got[2]):
            k = wp.atomic_add(order, 0, 1)
            log[2 * k] = got[0]
            log[2 * k + 1] = c
        if pool_finish(pool, got[0], got[2]):
            if got[0] == 0 and pool_resolve(pool, 1):
                pool_publish(pool, 1, chunks_b)
            pool_release(pool, got[0])


@wp.kernel
def toy_setup(pool: Pool, chunks_a: int, dependencies_b: int):
    a = pool_alloc(pool)
    b = pool_alloc(pool)
    pool_wait(pool, b, dependencies_b)
    pool_publish(pool, a, chunks_a)


def run_toy(chunks_a: int, chunks_b: int, dependencies_b: int = 1, min_chunks: int = 4,
            device: str = "cpu"):
    pool = make_pool(8, workers=1, min_chunks=min_chunks, device=device)
    order = wp.zeros(1, dtype=int, device=device)
    log = wp.full(2 * (chunks_a + chunks_b + 1), -1, dtype=int, device=device)
    wp.launch(toy_setup, dim=1, inputs=[pool, chunks_a, dependencies_b], device=device)
    wp.launch(toy_worker, dim=1, inputs=[pool, chunks_b, order, log], device=device)
    return pool, log.numpy().reshape(-1, 2)[: int(order.numpy()[0])]


def test_dependent_task_runs_after_the_task_it_waits_for(device):
    pool, log = run_toy(chunks_a=20, chunks_b=7, device=device)
    check_pool(pool)
    assert list(log[:, 0]) == [0] * 20 + [1] * 7
    assert sorted(log[:20, 1]) == list(range(20)) and sorted(log[20:, 1]) == list(range(7))


def test_chunks_are_taken_k_at_a_time(device):
    """Eq. 3.1 with W = 1: N_w = max(S, K) takes the whole step in one acquisition."""
    pool, log = run_toy(chunks_a=3, chunks_b=30, min_chunks=14, device=device)
    check_pool(pool)
    # One acquisition per task: chunks come in one descending-start block each.
    assert list(log[:3, 1]) == [0, 1, 2] and list(log[3:, 1]) == list(range(30))


def test_never_activated_dependency_is_reported_not_hung(device):
    pool, _ = run_toy(chunks_a=5, chunks_b=5, dependencies_b=2, device=device)
    with pytest.raises(PoolError, match="stuck with 1 unfinished tasks"):
        check_pool(pool)


def test_overflow_names_the_capacity():
    v, f = random_soup(np.random.default_rng(0), 5000)
    with pytest.raises(PoolError, match="all 2 slots were in use"):
        kernels.build_bvh(v, f, leaf_size=1, pool_capacity=2)


@pytest.mark.parametrize("method", ["sah", "median"])
def test_small_steps_run_inline(method):
    """K decides what goes through the pool; the tree is the same either way."""
    v, f = random_soup(np.random.default_rng(1), 3000)
    inline = kernels.build_bvh(v, f, method=method, min_chunks=1_000_000)
    pooled = kernels.build_bvh(v, f, method=method, min_chunks=1)
    middle = kernels.build_bvh(v, f, method=method, min_chunks=14)  # the paper's K
    assert inline.stats.pool_steps_published == 0
    assert pooled.stats.pool_steps_published > middle.stats.pool_steps_published > 0
    for other in (pooled, middle):
        assert other.stats.sah_cost == pytest.approx(inline.stats.sah_cost, rel=1e-12)
        assert other.stats.nodes == inline.stats.nodes


def test_several_workers_share_the_pool():
    """More workers than one: on CPU they run one after the other, so worker 0 does the work
    and the rest must find the pool empty and stop (not hang, not fail)."""
    v, f = random_soup(np.random.default_rng(2), 2000)
    one = kernels.build_bvh(v, f, workers=1)
    many = kernels.build_bvh(v, f, workers=64)
    assert many.stats.sah_cost == pytest.approx(one.stats.sah_cost, rel=1e-12)
