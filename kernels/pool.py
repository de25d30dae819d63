"""The persistent-worker task pool of the 2012 paper (Vinkler et al., sec. 3.3-3.4).

A task lives in a slot. `header[slot]` encodes its state in one int32 (sec. 3.4):
  > 0   active, with that many work chunks of the current step left to hand out
  < 0   dependent: waits for that many other tasks to finish
  = 0   locked: its data is being written
  <= EMPTY  free
The application keeps the task data (its own `@wp.struct` array) in the same slots;
`unfinished[slot]` counts the chunks of the current step not yet finished, so the worker that
brings it to zero is the last finisher and advances the task.

Here a worker is one thread (the paper's warp of 32 threads shares a chunk of 32 items; one
thread walks the chunk's items instead). On CPU a launch is one serial loop, so worker 0 does
all the work and the others find the pool empty; Warp's CPU atomics are plain
read-modify-writes, which is correct because of that. On CUDA, header reads go through
atomics and `memory_fence()` orders task data before the header that publishes it.
"""

from __future__ import annotations

import numpy as np
import warp as wp

EMPTY = wp.constant(-(1 << 30))
# state[] entries
LIVE = wp.constant(0)  # tasks stored and not finished; workers stop at zero
ERROR = wp.constant(1)  # 0, or one of the ERR_* codes below
HIGH_WATER = wp.constant(2)  # one past the highest slot ever used: bounds the search
PUBLISHED = wp.constant(3)  # later steps handed to the pool instead of run inline (sec. 3.4)
ERR_OVERFLOW = wp.constant(1)
ERR_STUCK = wp.constant(2)
STATE_SIZE = 4


@wp.struct
class Pool:
    header: wp.array(dtype=wp.int32)
    unfinished: wp.array(dtype=wp.int32)
    state: wp.array(dtype=wp.int32)
    capacity: int
    workers: int  # W in eq. 3.1
    min_chunks: int  # K in eq. 3.1 and the inline threshold of sec. 3.4
    max_idle: int  # empty searches in a row before a worker declares the pool stuck


class PoolError(RuntimeError):
    """The pool overflowed its capacity or stopped making progress."""


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    __threadfence();
#endif
"""
)
def memory_fence(): ...


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    return clock64();
#else
    return (int64_t)__builtin_readcyclecounter();
#endif
"""
)
def cycles() -> wp.int64: ...


@wp.func
def pool_load(a: wp.array(dtype=wp.int32), i: int) -> int:
    """Atomic read: on CUDA a plain load may be served from a stale cache line."""
    return wp.atomic_add(a, i, 0)


@wp.func
def pool_acquire(pool: Pool, start_slot: int) -> wp.vec3i:
    """Take work chunks from an active task (sec. 3.4, 'Retrieving work'), searching from
    `start_slot` downwards: workers start at different offsets to spread the atomics, and a
    worker starts where it worked last, so that it finishes a task and then a child before it
    turns to other tasks (depth first: the pool stays small).

    Returns (slot, first chunk, chunk count), or slot -1 when no active task was found."""
    used = pool_load(pool.state, HIGH_WATER)
    if used == 0:
        return wp.vec3i(-1, 0, 0)
    start = start_slot % used
    for j in range(used):  # downwards: the most recently stored tasks sit in high slots
        slot = (start - j + used) % used
        h = pool_load(pool.header, slot)
        if h > 0:
            # eq. 3.1: N_w = max(ceil(S / W), K)
            want = wp.max((h + pool.workers - 1) / pool.workers, pool.min_chunks)
            old = wp.atomic_sub(pool.header, slot, want)
            if old > 0:
                take = wp.min(want, old)
                return wp.vec3i(slot, old - take, take)
    return wp.vec3i(-1, 0, 0)


@wp.func
def pool_finish(pool: Pool, slot: int, count: int) -> bool:
    """Report `count` finished chunks; True for the last finisher of the step."""
    return wp.atomic_sub(pool.unfinished, slot, count) == count


@wp.func
def pool_publish(pool: Pool, slot: int, chunks: int):
    """Make the step of a locked task available: its data must be written before this."""
    pool.unfinished[slot] = chunks
    memory_fence()
    wp.atomic_exch(pool.header, slot, chunks)


@wp.func
def pool_hand_over(pool: Pool, slot: int, chunks: int):
    """Publish a task's next step, too big to run inline (counted in state[PUBLISHED])."""
    wp.atomic_add(pool.state, PUBLISHED, 1)
    pool_publish(pool, slot, chunks)


@wp.func
def pool_wait(pool: Pool, slot: int, dependencies: int):
    """Store a locked task as dependent on `dependencies` other tasks."""
    memory_fence()
    wp.atomic_exch(pool.header, slot, -dependencies)


@wp.func
def pool_resolve(pool: Pool, slot: int) -> bool:
    """One dependency of `slot` finished; True when it was the last (the task is now locked
    and the caller publishes its first step)."""
    return wp.atomic_add(pool.header, slot, 1) == -1


@wp.func
def pool_alloc(pool: Pool) -> int:
    """Claim a free slot by compare-and-swap to the locked state (sec. 3.4, 'Storing work').

    Returns -1 and flags ERR_OVERFLOW when every slot is taken."""
    for slot in range(pool.capacity):
        h = pool_load(pool.header, slot)
        if h <= EMPTY and wp.atomic_cas(pool.header, slot, h, 0) == h:
            wp.atomic_max(pool.state, HIGH_WATER, slot + 1)
            wp.atomic_add(pool.state, LIVE, 1)
            return slot
    wp.atomic_max(pool.state, ERROR, ERR_OVERFLOW)
    return -1


@wp.func
def pool_release(pool: Pool, slot: int):
    """The task in `slot` is done: free the slot."""
    wp.atomic_exch(pool.header, slot, EMPTY)
    wp.atomic_sub(pool.state, LIVE, 1)


@wp.func
def pool_running(pool: Pool) -> bool:
    return pool_load(pool.state, LIVE) > 0 and pool_load(pool.state, ERROR) == 0


def make_pool(capacity: int, workers: int, min_chunks: int, max_idle: int, device) -> Pool:
    pool = Pool()
    pool.header = wp.full(capacity, int(EMPTY), dtype=wp.int32, device=device)
    pool.unfinished = wp.zeros(capacity, dtype=wp.int32, device=device)
    pool.state = wp.zeros(STATE_SIZE, dtype=wp.int32, device=device)
    pool.capacity = capacity
    pool.workers = workers
    pool.min_chunks = min_chunks
    pool.max_idle = max_idle
    return pool


def check_pool(pool: Pool) -> np.ndarray:
    """Raise PoolError if the pool overflowed or stalled; return its state otherwise."""
    state = pool.state.numpy()
    if state[ERROR] == ERR_OVERFLOW:
        raise PoolError(
            f"task pool overflow: all {pool.capacity} slots were in use; "
            "pass a larger pool_capacity"
        )
    if state[ERROR] == ERR_STUCK or state[LIVE] != 0:
        raise PoolError(
            f"task pool stuck with {state[LIVE]} unfinished tasks (capacity {pool.capacity}, "
            f"{pool.workers} workers gave up after {pool.max_idle} empty searches)"
        )
    return state


def default_workers(device) -> int:
    """One worker on CPU (a launch is one serial loop); enough to fill a GPU otherwise."""
    device = wp.get_device(device)
    return 1 if device.is_cpu else 64 * device.sm_count * 4
