"""numpy in, numpy out: `dacrt_trace`, ray tracing without an acceleration structure."""

from __future__ import annotations

from typing import Any, Literal

import numpy as np

from ..core.hits import Hits
from ..core.launch import load_modules
from ..core.mesh import DeviceMesh
from ..core.validate import as_rays, ray_range
from ..pool.state import PoolOverflow
from . import breadth_first, task_pool
from .breadth_first import breadth_first_trace
from .options import DacrtOptions
from .records import margin_for
from .stats import DacrtStats
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
    stats: DacrtStats | None = None,
    options: DacrtOptions | None = None,
    **tuning: Any,
) -> Hits:
    """Closest hit per ray in [tmin, tmax] by divide-and-conquer ray tracing: the same
    `Hits` as `kernels.trace` on a BVH.

    variant "pool": the 2012 paper's task-pool DACRT, `split` "rdh" (the ray distribution
        heuristic) or "median"; "breadth_first": the 2013 paper's level-wise DACRT.
    options: a `DacrtOptions` (kernels.dacrt.options, every field documented there);
        keywords (`c_sort=4.0`, `alpha=32`, ...) set single fields of it. Fields left None
        take the device's default: the constants calibrated on CPUs there, the papers' GPU
        constants on CUDA.
    A `DacrtStats` passed as `stats` is filled with timings (ms, Warp's compile time apart
    as `compile_ms`), the bytes of device memory held at the peak, and task or level
    counts."""
    opts = (options or DacrtOptions()).with_(**tuning)
    mesh = DeviceMesh(vertices, indices, device)
    return dacrt_trace_mesh(mesh, origins, directions, tmin, tmax, variant, split,
                            stats=stats, options=opts)


def dacrt_trace_mesh(
    mesh: DeviceMesh,
    origins: np.ndarray,
    directions: np.ndarray,
    tmin: float | np.ndarray = 0.0,
    tmax: float | np.ndarray = np.inf,
    variant: Variant = "pool",
    split: Split = "rdh",
    *,
    stats: DacrtStats | None = None,
    options: DacrtOptions | None = None,
) -> Hits:
    """`dacrt_trace` on a mesh already on the device (a `Bvh`'s `mesh`, say): its triangle
    arrays are made once and reused by every call."""
    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {list(VARIANTS)}, got {variant!r}")
    if split not in SPLITS:
        raise ValueError(f"split must be one of {sorted(SPLITS)}, got {split!r}")
    origins, directions = as_rays(origins, directions)
    tmin_a, tmax_a = ray_range(tmin, tmax, len(origins))
    device = mesh.device
    opts = (options or DacrtOptions()).for_device(device)
    info = stats if stats is not None else DacrtStats()
    compile_ms = load_modules(device, *dacrt_warp_modules(variant))
    margin = margin_for(mesh.vertices, origins)
    if variant == "breadth_first":
        hits = breadth_first_trace(mesh, origins, directions, tmin_a, tmax_a, margin, info, opts)
        info.compile_ms = compile_ms
        return hits
    capacity = POOL_SLOTS if opts.pool_capacity is None else int(opts.pool_capacity)
    retries = 0
    while True:
        try:
            hits = pool_trace(mesh, origins, directions, tmin_a, tmax_a, margin, split, info,
                              opts, capacity)
        except PoolOverflow:
            if opts.pool_capacity is not None or capacity >= POOL_SLOTS_MAX:
                raise
            capacity *= 4  # the run stopped at the overflow: start again, bigger
            retries += 1
            continue
        info.fill(pool_capacity=capacity, pool_retries=retries, compile_ms=compile_ms)
        return hits


def dacrt_warp_modules(variant: Variant) -> tuple:
    """The Warp modules a trace of this variant runs (to load them before timing it)."""
    return task_pool.WARP_MODULES if variant == "pool" else breadth_first.WARP_MODULES
