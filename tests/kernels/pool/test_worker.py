"""A third application on the pool's one worker: segmented sums.

The example docs/architecture.md walks through ("Adding a pool application"). Each segment
of an int array is a task that sums it with the pool's PPS up-sweep (`pool.phases`): level 1
adds a chunk's values, the levels above add CHUNK sums at a time, one step per level, so a
long segment's early steps go through the pool and its late ones run inline. One more task
waits on all of them (a dependent task, sec. 3.4) and adds their totals; the last segment
to finish activates it and its worker continues with it.
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from scenesort.kernels.pool.chunks import CHUNK, level_count, level_size
from scenesort.kernels.pool.phases import pps_count, pps_total, pps_up_chunk
from scenesort.kernels.pool.state import (
    Pool,
    check_pool,
    make_pool,
    pool_alloc,
    pool_publish,
    pool_release,
    pool_resolve,
    pool_wait,
)
from scenesort.kernels.pool.worker import CYCLE_ROW, Application, launch_workers, make_worker

PH_SUM = wp.constant(0)  # one step per level of the segment's up-sweep
PH_TOTAL = wp.constant(1)  # the dependent task: one chunk
PH_DONE = wp.constant(2)
PHASE_NAMES = ("Sum", "Total", "Done")


@wp.struct
class SumTask:
    segment: int  # -1: the task that adds the segments' totals
    start: int
    count: int
    phase: int
    step: int
    chunks: int


@wp.struct
class SumData:
    values: wp.array(dtype=int)
    scan: wp.array(dtype=int)  # each segment's up-sweep levels, packed in its own range
    seg_start: wp.array(dtype=int)
    seg_count: wp.array(dtype=int)
    totals: wp.array(dtype=int)  # per segment
    grand: wp.array(dtype=int)  # [0]: the sum of the totals; [1]: the adding task's slot
    tasks: wp.array(dtype=SumTask)
    phase_cycles: wp.array(dtype=wp.int64)


@wp.func
def sum_chunks(t: SumTask) -> int:
    if t.phase == PH_SUM:
        return level_size(t.count, t.step + 1)
    return 1


@wp.func
def run_chunks(d: SumData, worker: int, slot: int, t: SumTask, first: int, count: int):
    for c in range(first, first + count):
        if t.phase == PH_TOTAL:
            s = int(0)
            for k in range(d.totals.shape[0]):
                s += d.totals[k]
            d.grand[0] = s
        elif t.step == 0:  # level 1: this application's own (PPS would count marks here)
            total = int(0)
            for i in range(t.start + c * CHUNK, wp.min(t.start + c * CHUNK + CHUNK,
                                                        t.start + t.count)):
                total += d.values[i]
            pps_count(d.scan, t.start, c, total)
        else:
            pps_up_chunk(d.scan, t.start, t.count, t.step + 1, c)


@wp.func
def complete_step(d: SumData, t: SumTask, slot: int) -> SumTask:
    if t.phase == PH_SUM and t.step < level_count(t.count) - 1:
        t.step += 1
        t.chunks = sum_chunks(t)
        return t
    if t.phase == PH_SUM:
        d.totals[t.segment] = pps_total(d.scan, t.start, t.count)
    t.phase = PH_DONE
    return t


@wp.func
def finish_task(d: SumData, pool: Pool, worker: int, t: SumTask, slot: int) -> int:
    pool_release(pool, slot)
    if t.segment < 0:
        return -1
    adder = d.grand[1]
    if pool_resolve(pool, adder):  # the last segment: continue with the adding task
        return adder
    return -1


sum_worker = make_worker(Application(
    data=SumData, task=SumTask, run_chunks=run_chunks, complete_step=complete_step,
    finish_task=finish_task, done=PH_DONE, module=__name__, name="segment_sum"))


@wp.kernel
def start_sums(d: SumData, pool: Pool):
    """The adding task waits on every segment; the segments are published."""
    adder = pool_alloc(pool)
    t = SumTask()
    t.segment = -1
    t.phase = PH_TOTAL
    t.chunks = 1
    d.tasks[adder] = t
    d.grand[1] = adder
    segments = d.seg_start.shape[0]
    pool_wait(pool, adder, segments)
    for k in range(segments):
        s = pool_alloc(pool)
        t = SumTask()
        t.segment = k
        t.start = d.seg_start[k]
        t.count = d.seg_count[k]
        t.phase = PH_SUM
        t.step = 0
        t.chunks = sum_chunks(t)
        d.tasks[s] = t
        pool_publish(pool, s, t.chunks)


def segment_sums(values: np.ndarray, counts: list[int], workers: int, min_chunks: int = 14,
                 device="cpu"):
    """(per-segment sums, their sum, pool state, phase cycles) of consecutive segments."""
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int32)
    d = SumData()
    d.values = wp.array(values, dtype=int, device=device)
    d.scan = wp.zeros(len(values), dtype=int, device=device)
    d.seg_start = wp.array(starts, dtype=int, device=device)
    d.seg_count = wp.array(np.asarray(counts, np.int32), dtype=int, device=device)
    d.totals = wp.zeros(len(counts), dtype=int, device=device)
    d.grand = wp.zeros(2, dtype=int, device=device)
    capacity = len(counts) + 1
    d.tasks = wp.empty(capacity, dtype=SumTask, device=device)
    d.phase_cycles = wp.zeros(workers * CYCLE_ROW, dtype=wp.int64, device=device)
    pool = make_pool(capacity, workers, min_chunks, device)
    wp.launch(start_sums, dim=1, inputs=[d, pool], device=device)
    launch_workers(sum_worker, workers, [d, pool], device)
    state = check_pool(pool)
    spent = d.phase_cycles.numpy().reshape(workers, -1)[:, : len(PHASE_NAMES)].sum(axis=0)
    return d.totals.numpy(), int(d.grand.numpy()[0]), state, spent


@pytest.mark.parametrize("workers", [1, 2])
@pytest.mark.parametrize("min_chunks", [1, 14, 1 << 20])
def test_segment_sums_on_the_pool_worker(workers, min_chunks, device):
    """Segments from 1 to 40,000 values (one to three levels; big steps through the pool,
    small ones inline, or everything inline with a huge K) give numpy's sums."""
    rng = np.random.default_rng(workers + min_chunks)
    counts = [1, 31, 32, 33, 1024, 1025, 40_000, *rng.integers(1, 5000, 20).tolist()]
    values = rng.integers(-1000, 1000, sum(counts)).astype(np.int32)
    totals, grand, state, spent = segment_sums(values, counts, workers, min_chunks, device)
    bounds = np.cumsum([0, *counts])
    expect = [int(values[a:b].sum()) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
    assert totals.tolist() == expect
    assert grand == int(values.sum())
    assert state[0] == 0  # no task left
    assert (state[3] > 0) == (min_chunks <= 14)  # steps handed to the pool (sec. 3.4)
    assert spent[0] > 0 and spent[2] > 0  # summing, and finishing tasks ("done")
