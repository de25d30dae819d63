"""numpy in, numpy out: `build_bvh` and `trace` (contract in docs/kernels-api.md)."""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import warp as wp

from . import bvh_build as bb
from .bvh_trace import STACK_SIZE, BvhArrays, trace_kernel
from .pool import check_pool, cpu_cores, default_workers, launch_workers, make_pool
from .validate import as_rays, as_triangle_mesh, per_ray

Method = Literal["sah", "median"]
METHODS: dict[str, int] = {"median": int(bb.METHOD_MEDIAN), "sah": int(bb.METHOD_SAH)}
DEFAULT_MIN_CHUNKS = 14  # K of eq. 3.1 (sec. 3.4)
PARTS_PER_THREAD = 8  # launch_split: parts per host thread, for load balance
MIN_PART = 4096  # launch_split: fewest items worth a launch of their own


@dataclass
class Hits:
    t: np.ndarray  # (R,) float32, inf on a miss
    triangle: np.ndarray  # (R,) int32, -1 on a miss
    u: np.ndarray  # (R,) float32 weight of v1
    v: np.ndarray  # (R,) float32 weight of v2

    @property
    def hit(self) -> np.ndarray:
        return self.triangle >= 0


@dataclass
class Bvh:
    vertices: np.ndarray
    indices: np.ndarray
    method: str
    leaf_size: int
    device: wp.context.Device
    arrays: BvhArrays  # device-side view for kernels
    bounds: np.ndarray  # (2, 3) float32
    stats: dict = field(default_factory=dict)
    _keep: tuple = ()  # the device arrays `arrays` points into

    def nodes(self) -> np.ndarray:
        """The node array as a numpy structured array (lo, first, hi, count)."""
        return self.arrays.nodes.numpy()

    def permutation(self) -> np.ndarray:
        """Caller's triangle index of each leaf position."""
        return self.arrays.tri_ids.numpy()


def _device(device) -> wp.context.Device:
    wp.init()
    return wp.get_device(device)


def _sync_ms(device, start: float) -> float:
    wp.synchronize_device(device)
    return (time.perf_counter() - start) * 1e3


def build_bvh(
    vertices: np.ndarray,
    indices: np.ndarray,
    method: Method = "sah",
    leaf_size: int = 8,
    max_depth: int = STACK_SIZE,
    device=None,
    *,
    min_chunks: int = DEFAULT_MIN_CHUNKS,
    workers: int | None = None,
    pool_capacity: int | None = None,
) -> Bvh:
    """Build a BVH with the task pool in one persistent launch (2012 paper, sec. 4)."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {sorted(METHODS)}, got {method!r}")
    if not 1 <= int(leaf_size) <= 64:
        raise ValueError(f"leaf_size must be in 1..64 (8, 16 or 32 are usual), got {leaf_size}")
    if not 1 <= int(max_depth) <= STACK_SIZE:
        raise ValueError(f"max_depth must be in 1..{STACK_SIZE}, got {max_depth}")
    if int(min_chunks) < 1:
        raise ValueError(f"min_chunks must be >= 1, got {min_chunks}")
    device = _device(device)
    phase_ms: dict[str, float] = {}
    wp.load_module(bb.build_worker.module, device=device)  # compile time is not build time
    t_total = t0 = time.perf_counter()
    vertices, indices = as_triangle_mesh(vertices, indices)
    phase_ms["validate"] = (time.perf_counter() - t0) * 1e3

    t0 = time.perf_counter()
    m = len(indices)
    workers = default_workers(device) if workers is None else int(workers)
    v_wp = wp.array(vertices, dtype=wp.vec3, device=device)
    f_wp = wp.array(indices, dtype=wp.vec3i, device=device)
    b = bb.BuildData()
    lo, hi = (wp.empty(m, dtype=wp.vec3, device=device) for _ in range(2))
    valid = wp.empty(m, dtype=int, device=device)
    inf = np.float32(np.inf)
    bounds = wp.array(np.array([[inf] * 3, [-inf] * 3, [inf] * 3, [-inf] * 3], np.float32),
                      dtype=wp.vec3, device=device)
    wp.launch(bb.triangle_boxes, dim=m,
              inputs=[v_wp, f_wp, lo, hi, valid, bounds], device=device)
    offsets = wp.empty(m, dtype=int, device=device)
    if m:
        wp.utils.array_scan(valid, offsets, inclusive=False)
    n = int(offsets.numpy()[-1] + valid.numpy()[-1]) if m else 0
    box = bounds.numpy()

    capacity = pool_capacity or (256 * workers if device.is_cpu else max(4096, 2 * n // leaf_size))
    b.perm, b.swap_id, b.swap_pos, b.scan = (
        wp.empty(max(n, 1), dtype=int, device=device) for _ in range(4)
    )
    b.tri_lo, b.tri_hi, b.swap_lo, b.swap_hi = (
        wp.empty(max(n, 1), dtype=wp.vec3, device=device) for _ in range(4)
    )
    b.mark = wp.empty(max(n, 1), dtype=wp.int8, device=device)
    b.box_lo, b.box_hi, b.cbox_lo, b.cbox_hi = (
        wp.empty(max(n, 1), dtype=wp.vec3, device=device) for _ in range(4)
    )
    bins = (capacity + workers) * bb.BIN_SLOTS  # per slot, then per worker
    b.bin_count = wp.empty(bins, dtype=int, device=device)
    b.bin_lo, b.bin_hi, b.bin_clo, b.bin_chi = (
        wp.empty(bins, dtype=wp.vec3, device=device) for _ in range(4)
    )
    b.tasks = wp.empty(capacity, dtype=bb.BuildTask, device=device)
    b.nodes = wp.empty(max(2 * n - 1, 1), dtype=bb.BvhNode, device=device)
    b.counters = wp.zeros(2, dtype=int, device=device)
    b.phase_cycles = wp.zeros(workers * bb.CYCLE_ROW, dtype=wp.int64, device=device)
    b.method = METHODS[method]
    b.leaf_size = int(leaf_size)
    b.max_depth = int(max_depth)
    pool = make_pool(capacity, workers, int(min_chunks), device)
    wp.launch(bb.compact_valid, dim=m, inputs=[valid, offsets, lo, hi, b],
              device=device)
    wp.launch(bb.reset_bins, dim=bins, inputs=[b], device=device)
    phase_ms["prepare"] = _sync_ms(device, t0)

    t0 = time.perf_counter()
    if n > 0:
        wp.launch(bb.start_build, dim=1,
                  inputs=[b, pool, *(wp.vec3(*row) for row in box), n], device=device)
        launch_workers(bb.build_worker, workers, [b, pool], device)
    pool_state = check_pool(pool)
    build_ms = _sync_ms(device, t0)
    cycles = b.phase_cycles.numpy().reshape(workers, -1)[:, : len(bb.PHASE_NAMES)]
    cycles = cycles.sum(axis=0).astype(np.float64)
    share = cycles / cycles.sum() if cycles.sum() > 0 else np.zeros_like(cycles)
    for name, s in zip(bb.PHASE_NAMES, share, strict=True):
        phase_ms[name] = float(build_ms * s)

    t0 = time.perf_counter()
    node_count, depth = (int(x) for x in b.counters.numpy())
    tri_verts = wp.empty(max(3 * n, 1), dtype=wp.vec3, device=device)
    wp.launch(bb.gather_leaf_triangles, dim=n, inputs=[v_wp, f_wp, b.perm, tri_verts],
              device=device)
    arrays = BvhArrays()
    arrays.nodes = b.nodes if n > 0 else _empty_root(device)
    arrays.tri_verts = tri_verts
    arrays.tri_ids = b.perm if n > 0 else wp.empty(0, dtype=int, device=device)
    phase_ms["reorder"] = _sync_ms(device, t0)
    total_ms = (time.perf_counter() - t_total) * 1e3

    bvh = Bvh(vertices=vertices, indices=indices, method=method, leaf_size=int(leaf_size),
              device=device, arrays=arrays, bounds=box[:2].copy(), _keep=(v_wp, f_wp))
    node_count = node_count if n > 0 else 1
    nodes = bvh.nodes()[:node_count]
    bvh.arrays.nodes = arrays.nodes[:node_count] if n > 0 else arrays.nodes
    leaves = int(np.count_nonzero(nodes["count"]))
    bvh.stats = {
        "build_ms": total_ms,
        "phase_ms": phase_ms,
        "nodes": node_count,
        "leaves": leaves if n > 0 else 0,
        "depth": depth,
        "sah_cost": sah_cost(nodes) if n > 0 else 0.0,
        "triangles": m,
        "degenerate": int(m - n),
        "pool_slots_used": int(pool_state[2]),
        "pool_steps_published": int(pool_state[3]),
        "workers": workers,
        "method": method,
        "leaf_size": int(leaf_size),
        "device": str(device),
    }
    return bvh


def degenerate_mask(vertices: np.ndarray, indices: np.ndarray, device=None,
                    threads: int | None = None) -> np.ndarray:
    """Zero-area triangles of a validated mesh, as `build_bvh` skips them (the float64 cross
    product of the float32 edges is exactly zero): a bool mask, computed on every core."""
    device = _device(device)
    m = len(indices)
    flags = np.empty(m, np.int8)
    out = to_device(flags, wp.int8, device)
    launch_split(bb.degenerate_flags, m, [to_device(vertices, wp.vec3, device)],
                 [to_device(np.ascontiguousarray(indices, np.int32), wp.vec3i, device)], [],
                 [out], device, _threads(device, threads))
    return (flags if device.is_cpu else out.numpy()).view(bool)


def count_degenerate(vertices: np.ndarray, indices: np.ndarray, device=None,
                     threads: int | None = None) -> int:
    """How many triangles `degenerate_mask` flags."""
    return int(np.count_nonzero(degenerate_mask(vertices, indices, device, threads)))


def _empty_root(device) -> wp.array:
    """The BVH of a mesh with no triangles: a root whose box, a point at infinity, no ray
    enters (an inverted box would look like all of space to the slab test)."""
    node = np.zeros(1, dtype=bb.BvhNode.numpy_dtype())
    node["lo"] = np.inf
    node["hi"] = np.inf
    return wp.array(node, dtype=bb.BvhNode, device=device)


def sah_cost(nodes: np.ndarray) -> float:
    """SAH cost with traversal and intersection cost 1: sum over nodes of A(node)/A(root)
    times 1 for inner nodes and times the triangle count for leaves."""
    raw = np.ascontiguousarray(nodes).view(np.float32).reshape(len(nodes), 8)  # 32-byte rows
    count = raw.view(np.int32)[:, 7]
    e = np.maximum(raw[:, 4:7] - raw[:, 0:3], np.float32(0.0))
    area = e[:, 0] * e[:, 1] + e[:, 1] * e[:, 2] + e[:, 2] * e[:, 0]  # float32: a statistic
    if area[0] <= 0:
        return float(count[0]) if len(nodes) == 1 else float(len(nodes))
    return float(np.dot(area.astype(np.float64), np.maximum(count, 1)) / float(area[0]))


def _threads(device, threads: int | None) -> int:
    if not device.is_cpu:
        return 1
    return cpu_cores() if threads is None else max(1, int(threads))


def trace(
    bvh: Bvh,
    origins: np.ndarray,
    directions: np.ndarray,
    tmin: float | np.ndarray = 0.0,
    tmax: float | np.ndarray = np.inf,
    any_hit: bool = False,
    *,
    threads: int | None = None,
) -> Hits:
    """Closest hit (or, with any_hit, some hit) per ray in [tmin, tmax].

    On CPU the rays are split between `threads` host threads (default: every core), each
    launching its share: a Warp CPU launch runs on one thread."""
    origins, directions = as_rays(origins, directions)
    r = len(origins)
    tmin_a = per_ray(tmin, r, "tmin", keep_scalar=True)
    tmax_a = per_ray(tmax, r, "tmax", keep_scalar=True)
    if np.any(tmax_a < tmin_a):
        raise ValueError("tmax must be >= tmin for every ray")
    device = bvh.device
    t, tri, u, v = (np.empty(r, dt) for dt in (np.float32, np.int32, np.float32, np.float32))
    outputs = [to_device(x, dt, device) for x, dt in ((t, float), (tri, int), (u, float),
                                                       (v, float))]
    inputs = [to_device(origins, wp.vec3, device), to_device(directions, wp.vec3, device),
              to_device(tmin_a, float, device), to_device(tmax_a, float, device)]
    launch_split(trace_kernel, r, [bvh.arrays], inputs, [int(any_hit)], outputs, device,
                 _threads(device, threads))
    if not device.is_cpu:
        t, tri, u, v = (a.numpy() for a in outputs)
    return Hits(t=t, triangle=tri, u=u, v=v)


def to_device(a: np.ndarray, dtype, device) -> wp.array:
    """A Warp view of a contiguous numpy array on CPU (no copy), a copy elsewhere."""
    return wp.array(a, dtype=dtype, device=device, copy=not device.is_cpu)


def launch_split(kernel, n: int, shared: list, per_item: list, scalars: list, outputs: list,
                 device, threads: int) -> None:
    """Launch `kernel` over n items, split into contiguous parts run by `threads` host
    threads (only on CPU, where a launch is serial). Arrays in `per_item` and `outputs`
    of length n are sliced per part; shorter ones (a broadcast scalar) are passed whole."""
    if n == 0:
        return
    # More parts than threads, taken in turn by the pool's threads: camera rays cost very
    # different amounts in different parts of the image (sky against geometry).
    parts = min(threads * PARTS_PER_THREAD, max(1, n // MIN_PART)) if threads > 1 else 1
    if parts <= 1:
        wp.launch(kernel, dim=n, inputs=[*shared, *per_item, *scalars], outputs=outputs,
                  device=device)
        return
    wp.load_module(kernel.module, device=device)  # compile once, not in every thread
    bounds = np.linspace(0, n, parts + 1).astype(int)

    def part(x: wp.array, a: int, b: int) -> wp.array:
        return x[a:b] if x.shape[0] == n else x

    def run(k: int) -> None:
        a, b = int(bounds[k]), int(bounds[k + 1])
        wp.launch(kernel, dim=b - a, inputs=[*shared, *(part(x, a, b) for x in per_item),
                                             *scalars],
                  outputs=[part(x, a, b) for x in outputs], device=device)

    with ThreadPoolExecutor(threads) as ex:
        list(ex.map(run, range(parts)))
