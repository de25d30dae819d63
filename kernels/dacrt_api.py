"""numpy in, numpy out: `dacrt_trace`, ray tracing without an acceleration structure."""

from __future__ import annotations

import time
from typing import Literal

import numpy as np
import warp as wp

from . import dacrt as dk
from . import dacrt_table
from .api import DEFAULT_MIN_CHUNKS, Hits, _threads, degenerate_mask, launch_split, to_device
from .pool import PoolOverflow, check_pool, default_workers, launch_workers, make_pool
from .validate import as_rays, as_triangle_mesh, per_ray

Variant = Literal["pool", "breadth_first"]
Split = Literal["rdh", "median"]
SPLITS: dict[str, int] = {"median": int(dk.SPLIT_MEDIAN), "rdh": int(dk.SPLIT_RDH)}
VARIANTS = ("pool", "breadth_first")
POOL_SLOTS = 1 << 12  # pool_capacity=None: the first try (~2.5 kB per slot) ...
POOL_SLOTS_MAX = 1 << 18  # ... grown 4x after an overflow, up to this
SMALL_ITEMS_CPU = 32768  # least small_items on CPU (measured: 4096 -> 32768 saved 3-7%)
MARGIN_REL = 2.0**-16  # box and plane widening, relative to the largest coordinate


def margin_for(vertices: np.ndarray, origins: np.ndarray) -> float:
    """Widening that covers the watertight test's rounding: a few float32 ulps of the
    largest coordinate in play, with a generous factor."""
    big = max(max(abs(float(x.max(initial=0.0))), abs(float(x.min(initial=0.0))))
              for x in (vertices, origins))
    return MARGIN_REL * max(big, 1e-30)


def scene_box(vertices: np.ndarray, indices: np.ndarray, ids: np.ndarray,
              margin: float) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) of the vertices that the triangles `ids` use, widened by the margin (a
    column-wise reduction over one copy: numpy's min(axis=0) of an (N, 3) array ran 10x
    slower, 18 ms of a 260 ms call on the buddha)."""
    used = np.zeros(len(vertices), bool)
    used[indices[ids]] = True
    columns = np.ascontiguousarray(vertices[used].T)
    return columns.min(axis=1) - margin, columns.max(axis=1) + margin


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
        from .pdacrt import pdacrt_trace  # here: pdacrt imports this module

        return pdacrt_trace(vertices, indices, ids, origins, directions, tmin_a, tmax_a,
                            margin_for(vertices, origins), device, info, int(alpha),
                            int(beta), int(max_depth), max(int(buffer_entries), 1))
    capacity = POOL_SLOTS if pool_capacity is None else int(pool_capacity)
    retries = 0
    while True:
        try:
            hits = _pool_trace(vertices, indices, ids, origins, directions, tmin_a, tmax_a,
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


class DeviceArrays:
    """Device arrays of one call, with the bytes they hold (peak memory accounting)."""

    def __init__(self, device):
        self.device = device
        self.bytes = 0
        self.peak = 0

    def new(self, shape, dtype, fill=None, data=None) -> wp.array:
        if data is not None:  # on CPU a view of the caller's (contiguous) array, no copy
            a = to_device(np.ascontiguousarray(data), dtype, self.device)
        elif fill is not None:
            a = wp.full(shape, fill, dtype=dtype, device=self.device)
        else:
            a = wp.empty(shape, dtype=dtype, device=self.device)
        self.bytes += a.capacity
        self.peak = max(self.peak, self.bytes)
        return a

    def free(self, *arrays: wp.array) -> None:
        for a in arrays:
            self.bytes -= a.capacity


def rays_and_triangles(mem: DeviceArrays, vertices, indices, origins, directions, tmin,
                       tmax) -> dk.DacrtData:
    """The DacrtData fields both variants share: the rays, and per triangle its vertices
    and box (the vertex and index uploads are freed once those are made)."""
    r, m = len(origins), len(indices)
    d = dk.DacrtData()
    d.directions = mem.new(max(r, 1), wp.vec3, data=directions if r else None)
    d.rays = mem.new(max(r, 1), dk.RayRecord)
    per_ray = [mem.new(r, dt, data=x) for x, dt in ((origins, wp.vec3), (tmin, float),
                                                   (tmax, float))]
    launch_split(dk.prepare_rays, r, [], [per_ray[0], d.directions, *per_ray[1:]], [],
                 [d.rays], mem.device, _threads(mem.device, None))
    mem.free(*per_ray)
    v_wp = mem.new(len(vertices), wp.vec3, data=vertices)
    f_wp = mem.new(m, wp.vec3i, data=indices)
    d.tri_verts = mem.new(max(3 * m, 1), wp.vec3)
    d.tri_lo = mem.new(max(m, 1), wp.vec3)
    d.tri_hi = mem.new(max(m, 1), wp.vec3)
    if m:
        wp.launch(dk.prepare_triangles, dim=m,
                  inputs=[v_wp, f_wp, d.tri_verts, d.tri_lo, d.tri_hi], device=mem.device)
    mem.free(v_wp, f_wp)
    return d


def write_hits(mem: DeviceArrays, d: dk.DacrtData, r: int) -> Hits:
    """Unpack every ray's closest-hit key (both variants), split over the host threads."""
    out = [mem.new(max(r, 1), dt) for dt in (float, int, float, float)]
    launch_split(dk.write_hits, r, [d.tri_verts], [d.rays, d.directions, d.best], [], out,
                 mem.device, _threads(mem.device, None))
    t, tri, u, v = (a.numpy()[:r] for a in out)
    return Hits(t=t, triangle=tri.astype(np.int32), u=u, v=v)


def _pool_trace(vertices, indices, ids, origins, directions, tmin, tmax, split, device,
                info, workers, min_chunks, capacity, max_depth, c_sort, c_inters, min_rays,
                min_tris, rdh_min_rays, small_items) -> Hits:
    wp.load_module(dk.dacrt_worker.module, device=device)  # compile time is not trace time
    t_start = time.perf_counter()
    mem = DeviceArrays(device)
    r, m, n = len(origins), len(indices), len(ids)
    d = rays_and_triangles(mem, vertices, indices, origins, directions, tmin, tmax)
    d.ray_ids = mem.new(max(r, 1), int, data=np.arange(max(r, 1), dtype=np.int32))
    d.tri_ids = mem.new(max(n, 1), int, data=ids if n else np.zeros(1, np.int32))
    for name, size, dtype in (("ray_cls", r, wp.int8), ("ray_mark", r, wp.int8),
                              ("ray_scan", r, int), ("ray_swap_id", r, int),
                              ("ray_swap_pos", r, int), ("tri_cls", m, wp.int8),
                              ("tri_mark", n, wp.int8), ("tri_scan", n, int),
                              ("tri_swap_id", n, int), ("tri_swap_pos", n, int),
                              ("box_lo", n, wp.vec3), ("box_hi", n, wp.vec3)):
        setattr(d, name, mem.new(max(size, 1), dtype))
    d.cand = mem.new(capacity * dk.CAND_INTS, wp.int32, fill=0)
    d.cand_lo = mem.new(capacity * dk.CAND_BOXES, wp.vec3, fill=wp.vec3(np.inf))
    d.cand_hi = mem.new(capacity * dk.CAND_BOXES, wp.vec3, fill=wp.vec3(-np.inf))
    d.neg = mem.new(capacity, wp.int32, fill=0)
    d.best = mem.new(max(r, 1), wp.uint64, fill=np.uint64(0xFFFFFFFFFFFFFFFF))
    d.tasks = mem.new(capacity, dk.DacrtTask)
    d.table = mem.new(dacrt_table.MASKS * dacrt_table.ROW, wp.int32,
                      data=dacrt_table.flat_table())
    d.counters = mem.new(dk.COUNTERS, wp.int32, fill=0)
    workers = default_workers(device) if workers is None else max(1, int(workers))
    d.phase_cycles = mem.new(workers * dk.PHASES, wp.int64, fill=0)
    d.split_method = SPLITS[split]
    d.rdh_min_rays = rdh_min_rays
    if small_items is None:
        small_items = max(SMALL_ITEMS_CPU, (r + n) // workers) if device.is_cpu else 0
    d.small_items = small_items
    d.margin = margin_for(vertices, origins)
    d.max_depth = max_depth
    d.c_inters = c_inters  # sec. 6.2: C_INTERS = 1, C_SORT = 80
    d.c_sort = c_sort
    d.min_rays = min_rays  # sec. 6.2: 32 rays, 16 triangles
    d.min_tris = min_tris
    pool = make_pool(capacity, workers, min_chunks, device)
    mem.bytes += 2 * capacity * 4
    mem.peak = max(mem.peak, mem.bytes)
    prepare_ms = (time.perf_counter() - t_start) * 1e3

    t0 = time.perf_counter()
    if r and n:
        box_lo, box_hi = scene_box(vertices, indices, ids, d.margin)
        wp.launch(dk.start_trace, dim=1,
                  inputs=[d, pool, wp.vec3(*box_lo), wp.vec3(*box_hi), r, n], device=device)
        launch_workers(dk.dacrt_worker, workers, [d, pool], device)
    counters = d.counters.numpy()
    if counters[dk.C_OVERFLOW]:
        raise RuntimeError("a DACRT leaf holds more than 2e9 ray-triangle pairs: the split "
                           "made no progress; lower max_depth or use variant='breadth_first'")
    state = check_pool(pool) if r and n else np.zeros(4, np.int32)
    wp.synchronize_device(device)
    trace_ms = (time.perf_counter() - t0) * 1e3

    t0 = time.perf_counter()
    hits = write_hits(mem, d, r)
    cycles = d.phase_cycles.numpy().reshape(workers, dk.PHASES).sum(axis=0).astype(np.float64)
    share = cycles / cycles.sum() if cycles.sum() > 0 else np.zeros_like(cycles)
    info.update({
        "variant": "pool",
        "split": split,
        "total_ms": (time.perf_counter() - t_start) * 1e3,
        "prepare_ms": prepare_ms,
        "trace_ms": trace_ms,
        "phase_ms": {name: float(trace_ms * s) for name, s in zip(dk.PHASE_NAMES, share,
                                                                   strict=True)},
        "peak_bytes": int(mem.peak),
        "tasks": int(counters[dk.C_TASKS]) + 1,
        "intersection_tasks": int(counters[dk.C_LEAVES]),
        "depth": int(counters[dk.C_MAX_DEPTH]),
        "rays_sorted": int(counters[dk.C_RAYS_SORTED]),
        "tris_sorted": int(counters[dk.C_TRIS_SORTED]),
        "pairs": 1000 * int(counters[dk.C_KPAIRS]),
        "intersection_rays": int(counters[dk.C_VISITS]),
        "intersection_rays_skipped": int(counters[dk.C_SKIPPED]),
        "pool_slots_used": int(state[2]),
        "workers": workers,
        "small_items": small_items,
        "degenerate": int(m - n),
    })
    return hits
