"""Real atomics for state that several launches share (the pool's workers, the host
threads claiming one call's chunks: core.claim), on CPU and on CUDA.

A Warp CPU launch is one serial loop and Warp's CPU atomics are plain read-modify-writes, so
on CPU each core runs its own launch of a worker kernel and every access to state shared
between workers goes through the functions below: `__atomic` builtins (sequentially
consistent, which also orders task data written before a header against the reads after
it). On CUDA they are CUDA's atomics, which are relaxed: `memory_fence()` (a no-op on CPU)
orders plain loads and stores around them where the pool hands data from one worker to
another (pool.state: a fence before the atomic that publishes, one after the atomic that
receives, so that a worker on another multiprocessor reads no stale L1 line).
"""

from __future__ import annotations

import warp as wp


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
    return *(volatile const int*)&a[i];
#else
    return __atomic_load_n(&a[i], __ATOMIC_SEQ_CST);
#endif
"""
)
def pool_load(a: wp.array(dtype=wp.int32), i: int) -> int:
    """Atomic read: a plain load may be served from a stale cache line or register. (On x86
    a plain `mov`, so idle workers polling the pool do not take the cache line away; on
    CUDA a volatile load, served by L2: an `atomicAdd(p, 0)` would serialise thousands of
    polling threads on the header's address.)"""
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
