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
thread walks the chunk's items instead). A Warp CPU launch is one serial loop and Warp's CPU
atomics are plain read-modify-writes, so on CPU each core runs its own launch of the worker
kernel and every access to state shared between workers goes through the `shared_*`
functions below: real atomics (`__atomic` builtins, sequentially consistent, which also
order the task data written before a header against the reads after it). On CUDA they are
CUDA's atomics, and `memory_fence()` orders task data before the header that publishes it.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import warp as wp

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


@wp.struct
class Pool:
    header: wp.array(dtype=wp.int32)
    unfinished: wp.array(dtype=wp.int32)
    stamp: wp.array(dtype=wp.int32)  # per slot: the publication count when its step came
    state: wp.array(dtype=wp.int32)
    capacity: int
    workers: int  # W in eq. 3.1
    min_chunks: int  # K in eq. 3.1 and the inline threshold of sec. 3.4
    max_idle: wp.int64  # cycles without work before a worker declares the pool stuck


class PoolError(RuntimeError):
    """The pool overflowed its capacity or stopped making progress."""


class PoolOverflow(PoolError):
    """Every slot of the pool was in use (the workers stopped at once)."""


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
    return atomicAdd(&a[i], v);
#else
    return __atomic_fetch_add(&a[i], v, __ATOMIC_SEQ_CST);
#endif
"""
)
def shared_add(a: wp.array(dtype=wp.int32), i: int, v: int) -> int: ...


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    return atomicExch(&a[i], v);
#else
    return __atomic_exchange_n(&a[i], v, __ATOMIC_SEQ_CST);
#endif
"""
)
def shared_exch(a: wp.array(dtype=wp.int32), i: int, v: int) -> int: ...


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    return atomicCAS(&a[i], expected, v);
#else
    __atomic_compare_exchange_n(&a[i], &expected, v, false, __ATOMIC_SEQ_CST, __ATOMIC_SEQ_CST);
    return expected;
#endif
"""
)
def shared_cas(a: wp.array(dtype=wp.int32), i: int, expected: int, v: int) -> int: ...


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    return atomicMax(&a[i], v);
#else
    return __atomic_fetch_max(&a[i], v, __ATOMIC_SEQ_CST);
#endif
"""
)
def shared_max(a: wp.array(dtype=wp.int32), i: int, v: int) -> int: ...


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    wp::atomic_min(&a[i], v);
#else
    for (int k = 0; k < 3; ++k) {
        float* p = &a[i].c[k];
        float old;
        __atomic_load(p, &old, __ATOMIC_SEQ_CST);
        while (v.c[k] < old &&
               !__atomic_compare_exchange(p, &old, &v.c[k], false, __ATOMIC_SEQ_CST,
                                          __ATOMIC_SEQ_CST)) {}
    }
#endif
"""
)
def shared_min_vec3(a: wp.array(dtype=wp.vec3), i: int, v: wp.vec3): ...


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    wp::atomic_max(&a[i], v);
#else
    for (int k = 0; k < 3; ++k) {
        float* p = &a[i].c[k];
        float old;
        __atomic_load(p, &old, __ATOMIC_SEQ_CST);
        while (v.c[k] > old &&
               !__atomic_compare_exchange(p, &old, &v.c[k], false, __ATOMIC_SEQ_CST,
                                          __ATOMIC_SEQ_CST)) {}
    }
#endif
"""
)
def shared_max_vec3(a: wp.array(dtype=wp.vec3), i: int, v: wp.vec3): ...


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


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    return atomicAdd(&a[i], 0);
#else
    return __atomic_load_n(&a[i], __ATOMIC_SEQ_CST);
#endif
"""
)
def pool_load(a: wp.array(dtype=wp.int32), i: int) -> int:
    """Atomic read: a plain load may be served from a stale cache line or register. (On x86
    a plain `mov`, so idle workers polling the pool do not take the cache line away.)"""
    ...


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    __nanosleep(100);
#elif defined(__x86_64__)
    __builtin_ia32_pause();
#elif defined(__aarch64__)
    __asm__ __volatile__("yield");
#endif
"""
)
def cpu_relax(): ...


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
                return wp.vec3i(slot, h - take, take)
            h = seen


@wp.func
def pool_finish(pool: Pool, slot: int, count: int) -> bool:
    """Report `count` finished chunks; True for the last finisher of the step."""
    return shared_add(pool.unfinished, slot, -count) == count


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
    and the caller publishes its first step)."""
    return shared_add(pool.header, slot, 1) == -1


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
    """Call when a search found no work; returns the cycle count the worker has been idle
    since. After `max_idle` cycles without work the pool is declared stuck (ERR_STUCK), so
    that a lost dependency ends the launch with an error instead of a hang."""
    cpu_relax()
    now = cycles()
    if idle_since < wp.int64(0):
        return now
    if now - idle_since > pool.max_idle:
        shared_max(pool.state, ERROR, ERR_STUCK)
    return idle_since


# Cycles a worker may wait for work while others still hold some (about 10 s): only a lost
# dependency waits that long. A lone worker with nothing to do is stuck at once.
WAIT_CYCLES = 30_000_000_000


def make_pool(capacity: int, workers: int, min_chunks: int, device,
              max_idle: int | None = None) -> Pool:
    pool = Pool()
    pool.header = wp.full(capacity, int(EMPTY), dtype=wp.int32, device=device)
    pool.unfinished = wp.zeros(capacity, dtype=wp.int32, device=device)
    pool.stamp = wp.zeros(capacity, dtype=wp.int32, device=device)
    pool.state = wp.zeros(STATE_SIZE, dtype=wp.int32, device=device)
    pool.capacity = capacity
    pool.workers = workers
    pool.min_chunks = min_chunks
    pool.max_idle = wp.int64((0 if workers == 1 else WAIT_CYCLES) if max_idle is None else max_idle)
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
        raise PoolError(
            f"task pool stuck with {state[LIVE]} unfinished tasks (capacity {pool.capacity}, "
            f"{pool.workers} workers found no work for {pool.max_idle} cycles)"
        )
    return state


def cpu_cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()


def default_workers(device) -> int:
    """One worker per core on CPU (each a launch of its own); enough to fill a GPU."""
    device = wp.get_device(device)
    return cpu_cores() if device.is_cpu else 64 * device.sm_count * 4


def launch_workers(kernel, workers: int, inputs: list, device) -> None:
    """Launch a persistent worker kernel whose last argument is the first worker's index:
    on CPU one launch of one worker per host thread, so the workers run in parallel."""
    if not wp.get_device(device).is_cpu or workers == 1:
        wp.launch(kernel, dim=workers, inputs=[*inputs, 0], device=device)
        return
    wp.load_module(kernel.module, device=device)
    with ThreadPoolExecutor(workers) as ex:
        futures = [
            ex.submit(wp.launch, kernel, dim=1, inputs=[*inputs, w], device=device)
            for w in range(workers)
        ]
        for f in futures:
            f.result()
