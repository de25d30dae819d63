"""numpy in, numpy out: `dacrt_trace`, ray tracing without an acceleration structure."""

from __future__ import annotations

from typing import Literal

import numpy as np
import warp as wp

from ..core.hits import Hits
from ..core.mesh import degenerate_mask
from ..core.validate import as_rays, as_triangle_mesh, per_ray
from ..pool.state import DEFAULT_MIN_CHUNKS, PoolOverflow
from .breadth_first import breadth_first_trace
from .records import margin_for
from .task_pool import SPLITS, pool_trace

Variant = Literal["pool", "breadth_first"]
Split = Literal["rdh", "median"]
VARIANTS = ("pool", "breadth_first")
POOL_SLOTS = 1 << 12  # pool_capacity=None: the first try (~2.5 kB per slot) ...
POOL_SLOTS_MAX = 1 << 18  # ... grown 4x after an overflow, up to this


def dacrt_trace(
    vertices: np.ndarray,
    indices: np.ndarray,
    origins: np.ndarray,
    directions: np.ndarray,
    tmin: float | np.ndarray = 0.0,
    tmax: float | np.ndarray = np.inf,
    variant: Variant = "pool",
    split: Split = "rdh",
    device=None,
    *,
    stats: dict | None = None,
    workers: int | None = None,
    min_chunks: int = DEFAULT_MIN_CHUNKS,
    pool_capacity: int | None = None,
    max_depth: int = 48,
    alpha: int = 256,
    beta: int = 256,
    buffer_entries: int = 1 << 20,
    c_sort: float = 80.0,
    c_inters: float = 1.0,
    min_rays: int = 32,
    min_tris: int = 16,
    rdh_min_rays: int = 4096,
    small_items: int | None = None,
) -> Hits:
    """Closest hit per ray in [tmin, tmax] by divide-and-conquer ray tracing: the same
    `Hits` as `kernels.trace` on a BVH.

    variant "pool": the 2012 paper's task-pool DACRT; `split` "rdh" or "median"; its
        termination rule #tris #rays c_inters < (#tris + #rays) c_sort, or fewer than
        min_rays rays or min_tris triangles (sec. 5.2, 6.2). RDH samples tasks with at least
        rdh_min_rays rays and takes the spatial median in smaller ones, where sqrt(#rays)
        samples estimate little and cost about what they save. A task of at most small_items
        rays + triangles runs PPS1 to AABB as one counting sort in one worker (the PPS
        rounds' steps and scans cost more than the work, as long as other tasks keep the
        other workers busy); default on CPU: a worker's share of all rays and triangles
        (at least SMALL_ITEMS_CPU), so only the tasks above it (the root, with two workers)
        run the paper's phases in parallel; on CUDA 0 (the paper's phases in every task),
        where one thread per task would leave the device idle.
    variant "breadth_first": the 2013 paper's level-wise DACRT; alpha, beta: its
        terminal-node thresholds; buffer_entries: the terminal buffer's flush threshold.
    pool_capacity: task-pool slots; None starts with POOL_SLOTS and, if the tasks alive at
        once outgrow them (many incoherent rays), runs again with 4x as many (stats
        "pool_retries"); an explicit capacity raises PoolError instead.
    Defaults are the papers' (GPU) constants. A dict passed as `stats` receives timings
    (ms), the bytes of device memory held at the peak, and task or level counts."""
    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {list(VARIANTS)}, got {variant!r}")
    if split not in SPLITS:
        raise ValueError(f"split must be one of {sorted(SPLITS)}, got {split!r}")
    if int(min_chunks) < 1:
        raise ValueError(f"min_chunks must be >= 1, got {min_chunks}")
    if not 1 <= int(max_depth) <= 64:
        raise ValueError(f"max_depth must be in 1..64, got {max_depth}")
    if int(alpha) < 1 or int(beta) < 1:
        raise ValueError(f"alpha and beta must be >= 1, got {alpha} and {beta}")
    vertices, indices = as_triangle_mesh(vertices, indices)
    origins, directions = as_rays(origins, directions)
    r = len(origins)
    tmin_a = per_ray(tmin, r, "tmin")
    tmax_a = per_ray(tmax, r, "tmax")
    if np.any(tmax_a < tmin_a):
        raise ValueError("tmax must be >= tmin for every ray")
    wp.init()
    device = wp.get_device(device)
    ids = np.flatnonzero(~degenerate_mask(vertices, indices, "cpu")).astype(np.int32)
    info = stats if stats is not None else {}
    if variant == "breadth_first":
        return breadth_first_trace(vertices, indices, ids, origins, directions, tmin_a, tmax_a,
                            margin_for(vertices, origins), device, info, int(alpha),
                            int(beta), int(max_depth), max(int(buffer_entries), 1))
    capacity = POOL_SLOTS if pool_capacity is None else int(pool_capacity)
    retries = 0
    while True:
        try:
            hits = pool_trace(vertices, indices, ids, origins, directions, tmin_a, tmax_a,
                               split, device, info, workers, int(min_chunks), capacity,
                               int(max_depth), float(c_sort), float(c_inters),
                               int(min_rays), int(min_tris), int(rdh_min_rays),
                               None if small_items is None else int(small_items))
        except PoolOverflow:
            if pool_capacity is not None or capacity >= POOL_SLOTS_MAX:
                raise
            capacity *= 4  # the run stopped at the overflow: start again, bigger
            retries += 1
            continue
        info.update(pool_capacity=capacity, pool_retries=retries)
        return hits
