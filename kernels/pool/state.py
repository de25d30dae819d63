"""The persistent-worker task pool of the 2012 paper (Vinkler et al., sec. 3.3-3.4).

A task lives in a slot. `header[slot]` encodes its state in one int32 (sec. 3.4):
  > 0   active, with that many work chunks of the current step left to hand out
  < 0   dependent: waits for that many other tasks to finish
  = 0   locked: its data is being written
  <= EMPTY  free
The application keeps the task data (its own `@wp.struct` array) in the same slots;
`unfinished[slot]` counts the chunks of the current step not yet finished, so the worker that
brings it to zero is the last finisher and advances the task.

Every access to state that workers share goes through the real atomics of `atomics.py`.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..core.atomics import (
    cpu_relax,
    memory_fence,
    pool_load,
    shared_add,
    shared_cas,
    shared_exch,
    shared_max,
)
from ..core.launch import cpu_cores
from .clock import ticks, ticks_per_second

EMPTY = wp.constant(-(1 << 30))
# state[] entries
LIVE = wp.constant(0)  # tasks stored and not finished; workers stop at zero
ERROR = wp.constant(1)  # 0, or one of the ERR_* codes below
HIGH_WATER = wp.constant(2)  # one past the highest slot ever used: bounds the search
PUBLISHED = wp.constant(3)  # later steps handed to the pool instead of run inline (sec. 3.4)
STAMPS = wp.constant(4)  # publications so far (stamps them; 2^31 per pool is plenty)
ERR_OVERFLOW = wp.constant(1)
ERR_STUCK = wp.constant(2)
STATE_SIZE = 5
DEFAULT_MIN_CHUNKS = 14  # K of eq. 3.1 (sec. 3.4)


@wp.struct
class Pool:
    header: wp.array(dtype=wp.int32)
    unfinished: wp.array(dtype=wp.int32)
    stamp: wp.array(dtype=wp.int32)  # per slot: the publication count when its step came
    state: wp.array(dtype=wp.int32)
    capacity: int
    workers: int  # W in eq. 3.1
    min_chunks: int  # K in eq. 3.1 and the inline threshold of sec. 3.4
    max_idle: wp.int64  # clock ticks without work before a worker declares the pool stuck


class PoolError(RuntimeError):
    """The pool overflowed its capacity or stopped making progress."""


class PoolOverflow(PoolError):
    """Every slot of the pool was in use (the workers stopped at once)."""


@wp.func
def pool_acquire(pool: Pool) -> wp.vec3i:
    """Take work chunks from an active task (sec. 3.4, 'Retrieving work'): the one whose
    step was published last, so that workers go depth first and the pool stays small. (A
    search from the worker's last slot, as first written here, is not depth first once
    slots are reused: DACRT on 1.8 M incoherent rays kept ~4000 tasks alive instead of
    ~200, and ran 20% slower.) The scan reads every used header: cheap for a few CPU
    workers; thousands of GPU workers might rather search from spread offsets (not run).

    The chunks are taken with a compare-and-swap of the header value just read rather than
    the paper's blind decrement: a decrement based on a stale read could land on a slot that
    has since been reused for a dependent task and corrupt its dependency count.
    Returns (slot, first chunk, chunk count), or slot -1 when no active task was found."""
    used = pool_load(pool.state, HIGH_WATER)
    while True:
        slot = int(-1)
        newest = int(-1)
        for k in range(used):
            if pool_load(pool.header, k) > 0:
                stamp = pool_load(pool.stamp, k)
                if stamp > newest:
                    newest = stamp
                    slot = k
        if slot < 0:
            return wp.vec3i(-1, 0, 0)
        h = pool_load(pool.header, slot)
        while h > 0:
            # eq. 3.1: N_w = max(ceil(S / W), K)
            want = wp.max((h + pool.workers - 1) / pool.workers, pool.min_chunks)
            take = wp.min(want, h)
            seen = shared_cas(pool.header, slot, h, h - take)
            if seen == h:
                memory_fence()  # acquire: the task's data, published before its header
                return wp.vec3i(slot, h - take, take)
            h = seen


@wp.func
def pool_finish(pool: Pool, slot: int, count: int) -> bool:
    """Report `count` finished chunks; True for the last finisher of the step, which then
    sees every other finisher's results (the fences: release before, acquire after)."""
    memory_fence()
    last = shared_add(pool.unfinished, slot, -count) == count
    if last:
        memory_fence()
    return last


@wp.func
def pool_publish(pool: Pool, slot: int, chunks: int):
    """Make the step of a locked task available: its data must be written before this."""
    shared_exch(pool.unfinished, slot, chunks)
    shared_exch(pool.stamp, slot, shared_add(pool.state, STAMPS, 1))
    memory_fence()
    shared_exch(pool.header, slot, chunks)


@wp.func
def pool_hand_over(pool: Pool, slot: int, chunks: int):
    """Publish a task's next step, too big to run inline (counted in state[PUBLISHED])."""
    shared_add(pool.state, PUBLISHED, 1)
    pool_publish(pool, slot, chunks)


@wp.func
def pool_wait(pool: Pool, slot: int, dependencies: int):
    """Store a locked task as dependent on `dependencies` other tasks."""
    memory_fence()
    shared_exch(pool.header, slot, -dependencies)


@wp.func
def pool_resolve(pool: Pool, slot: int) -> bool:
    """One dependency of `slot` finished; True when it was the last (the task is now locked
    and the caller publishes its first step, seeing what the finished tasks wrote)."""
    memory_fence()
    last = shared_add(pool.header, slot, 1) == -1
    if last:
        memory_fence()
    return last


@wp.func
def pool_alloc(pool: Pool) -> int:
    """Claim a free slot by compare-and-swap to the locked state (sec. 3.4, 'Storing work').

    Returns -1 and flags ERR_OVERFLOW when every slot is taken."""
    for slot in range(pool.capacity):
        h = pool_load(pool.header, slot)
        if h <= EMPTY and shared_cas(pool.header, slot, h, 0) == h:
            shared_max(pool.state, HIGH_WATER, slot + 1)
            shared_add(pool.state, LIVE, 1)
            return slot
    shared_max(pool.state, ERROR, ERR_OVERFLOW)
    return -1


@wp.func
def pool_release(pool: Pool, slot: int):
    """The task in `slot` is done: free the slot."""
    shared_exch(pool.header, slot, EMPTY)
    shared_add(pool.state, LIVE, -1)


@wp.func
def pool_running(pool: Pool) -> bool:
    return pool_load(pool.state, LIVE) > 0 and pool_load(pool.state, ERROR) == 0


@wp.func
def pool_idle(pool: Pool, idle_since: wp.int64) -> wp.int64:
    """Call when a search found no work; returns the clock reading (pool.clock) the worker
    has been idle since. After `max_idle` ticks without work the pool is declared stuck
    (ERR_STUCK), so that a lost dependency ends the launch with an error instead of a hang."""
    cpu_relax()
    now = ticks()
    if idle_since < wp.int64(0):
        return now
    if now - idle_since > pool.max_idle:
        shared_max(pool.state, ERROR, ERR_STUCK)
    return idle_since


# Seconds a worker may wait for work while others still hold some: only a lost dependency
# waits that long. A lone worker with nothing to do is stuck at once. Converted to ticks of
# the device's clock, whose rate varies from 24 MHz to a few GHz (pool.clock).
WAIT_SECONDS = 10.0


def make_pool(capacity: int, workers: int, min_chunks: int, device,
              wait_seconds: float | None = None) -> Pool:
    """An empty pool of `capacity` slots for `workers` workers; an idle worker declares it
    stuck after `wait_seconds` (WAIT_SECONDS; 0 for a lone worker) without work."""
    pool = Pool()
    pool.header = wp.full(capacity, int(EMPTY), dtype=wp.int32, device=device)
    pool.unfinished = wp.zeros(capacity, dtype=wp.int32, device=device)
    pool.stamp = wp.zeros(capacity, dtype=wp.int32, device=device)
    pool.state = wp.zeros(STATE_SIZE, dtype=wp.int32, device=device)
    pool.capacity = capacity
    pool.workers = workers
    pool.min_chunks = min_chunks
    if wait_seconds is None:
        wait_seconds = 0.0 if workers == 1 else WAIT_SECONDS
    rate = ticks_per_second(device) if wait_seconds > 0 else 0.0
    pool.max_idle = wp.int64(int(wait_seconds * rate))
    return pool


def check_pool(pool: Pool) -> np.ndarray:
    """Raise PoolError if the pool overflowed or stalled; return its state otherwise."""
    state = pool.state.numpy()
    if state[ERROR] == ERR_OVERFLOW:
        raise PoolOverflow(
            f"task pool overflow: all {pool.capacity} slots were in use; "
            "pass a larger pool_capacity"
        )
    if state[ERROR] == ERR_STUCK or state[LIVE] != 0:
        idle = int(pool.max_idle)
        waited = idle / ticks_per_second(pool.state.device) if idle > 0 else 0.0
        raise PoolError(
            f"task pool stuck with {state[LIVE]} unfinished tasks (capacity {pool.capacity}, "
            f"{pool.workers} workers found no work for {waited:.3g} s)"
        )
    return state


def default_workers(device, per_sm: int = 256) -> int:
    """One worker per core on CPU (each a launch of its own); on CUDA `per_sm` one-thread
    workers per multiprocessor: the build ran best with 256 on an H200, the task-pool DACRT
    with 32 (docs/benchmarks.md, CUDA sweeps)."""
    device = wp.get_device(device)
    return cpu_cores() if device.is_cpu else per_sm * device.sm_count
