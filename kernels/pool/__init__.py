"""The task pool of the 2012 paper (sec. 3.3-3.4): its state in device memory (shared
through core.atomics), the clock its workers time phases and idle waits with, work chunks
and reduction trees, and the launch of persistent workers."""

from .state import DEFAULT_MIN_CHUNKS, Pool, PoolError, PoolOverflow, check_pool, make_pool

__all__ = ["DEFAULT_MIN_CHUNKS", "Pool", "PoolError", "PoolOverflow", "check_pool", "make_pool"]
