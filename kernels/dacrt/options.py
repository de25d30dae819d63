"""Tuning of `dacrt_trace`: one frozen dataclass, with the defaults that depend on the device.

The papers' constants (2012 paper, sec. 6.2: C_SORT = 80, intersection tasks below 32 rays
or 16 triangles; 2013 paper: alpha = beta = 256 for the terminal nodes) fit a GPU, where a
warp of 32 threads sorts 32 items in the time of one. On one CPU thread a sorting step per
item costs about as much as a few intersection tests, and the constants calibrated on these
CPUs (docs/benchmarks.md, DACRT notes) run 2-3x faster: C_SORT = 4 and 16 rays for the task
pool (Sponza 512², RDH: 1.31 s against 3.6 s), alpha = 32 and beta = 128 for the
breadth-first variant (1.6 s against 4.1 s). `for_device` fills in those of the device a
trace runs on; CUDA keeps the papers' (not run on a GPU here).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

from ..pool.state import DEFAULT_MIN_CHUNKS

# device kind -> the defaults that depend on it
DEVICE_DEFAULTS: dict[str, dict[str, float | int]] = {
    "cpu": {"c_sort": 4.0, "min_rays": 16, "alpha": 32, "beta": 128},
    "cuda": {"c_sort": 80.0, "min_rays": 32, "alpha": 256, "beta": 256},  # the papers'
}


@dataclass(frozen=True)
class DacrtOptions:
    """How `dacrt_trace` divides and conquers; None: the default for the device.

    Task-pool variant (2012 paper, sec. 5):
      workers: pool workers (one per core on CPU; on CUDA task_pool.WORKERS_PER_SM per
          multiprocessor).
      min_chunks: K of eq. 3.1; steps with fewer chunks run inline (sec. 3.4).
      pool_capacity: task-pool slots; None starts with POOL_SLOTS and, if the tasks alive
          at once outgrow them (many incoherent rays), runs again with 4x as many (stats
          "pool_retries"); a number raises PoolError on an overflow instead.
      max_depth: subdivision levels at most (both variants).
      c_sort, c_inters, min_rays, min_tris: the termination rule of sec. 5.2, 6.2: a task
          intersects when #tris #rays c_inters < (#tris + #rays) c_sort, or it has fewer
          than min_rays rays or min_tris triangles. CPU: c_sort 4, min_rays 16; CUDA: the
          paper's 80 and 32.
      rdh_min_rays: RDH samples tasks with at least this many rays and takes the spatial
          median in smaller ones, where sqrt(#rays) samples estimate little and cost about
          what they save.
      small_items: a task of at most this many rays + triangles runs PPS1 to AABB as one
          counting sort in one worker. None: on CPU a worker's share of all rays and
          triangles (at least SMALL_ITEMS_CPU), so only the tasks above it run the paper's
          phases in parallel; on CUDA 0 (the paper's phases in every task).
    Breadth-first variant (2013 paper):
      alpha, beta: nodes with fewer triangles (alpha) or rays (beta) are terminal. CPU: 32
          and 128; CUDA: the paper's 256 and 256.
      buffer_entries: the terminal buffer's flush threshold.
    """

    workers: int | None = None
    min_chunks: int = DEFAULT_MIN_CHUNKS
    pool_capacity: int | None = None
    max_depth: int = 48
    c_sort: float | None = None
    c_inters: float = 1.0
    min_rays: int | None = None
    min_tris: int = 16
    rdh_min_rays: int = 4096
    small_items: int | None = None
    alpha: int | None = None
    beta: int | None = None
    buffer_entries: int = 1 << 20

    def __post_init__(self) -> None:
        if int(self.min_chunks) < 1:
            raise ValueError(f"min_chunks must be >= 1, got {self.min_chunks}")
        if not 1 <= int(self.max_depth) <= 64:
            raise ValueError(f"max_depth must be in 1..64, got {self.max_depth}")
        for name in ("alpha", "beta"):
            value = getattr(self, name)
            if value is not None and int(value) < 1:
                raise ValueError(f"alpha and beta must be >= 1, got {name}={value}")

    def with_(self, **changes) -> DacrtOptions:
        """A copy with these fields changed (None values are left as they are); an unknown
        name raises TypeError naming it."""
        known = {f.name for f in fields(self)}
        unknown = sorted(set(changes) - known)
        if unknown:
            raise TypeError(f"unknown DACRT option(s) {unknown}; the options are {sorted(known)}")
        return replace(self, **{k: v for k, v in changes.items() if v is not None})

    def for_device(self, device) -> DacrtOptions:
        """The options with every device-dependent default filled in for `device`."""
        kind = "cpu" if device.is_cpu else "cuda"
        return replace(self, **{k: v for k, v in DEVICE_DEFAULTS[kind].items()
                                if getattr(self, k) is None})
