"""numpy in, numpy out: `build_bvh` and `trace` (contract in docs/kernels-api.md)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
import warp as wp

from ..core.claim import claimed_arg, launch_claimed
from ..core.hits import Hits
from ..core.launch import (
    get_device,
    host_threads,
    load_modules,
    part_launcher,
    run_parts,
    sync_ms,
)
from ..core.mesh import DeviceMesh
from ..core.validate import as_rays_unread, as_triangle_mesh, ray_range, refuse_flagged_rays
from ..pool.chunks import CHUNK
from ..pool.state import check_pool, default_workers, make_pool
from ..pool.worker import CYCLE_ROW, launch_workers
from . import build as bb
from .binary_traversal import STACK_SIZE
from .build_data import (
    BINS,
    METHOD_MEDIAN,
    METHOD_SAH,
    PHASE_NAMES,
    SUBTREE_NODES,
    BuildData,
    BuildItem,
    BuildTask,
)
from .node import BvhArrays, BvhNode, empty_root, sah_cost
from .packet import PACKET, packet_trace_kernel, packets_apply
from .stats import BvhStats
from .traversal import trace_kernel
from .wide import WHOLE, WIDE_STACK, WIDTHS, collapse, collapse_kernel, empty_wide
from .wide_traversal import simd_support

Method = Literal["sah", "median"]
METHODS: dict[str, int] = {"median": int(METHOD_MEDIAN), "sah": int(METHOD_SAH)}
Width = Literal[2, 4, 8]
# width=None: the faster traversal per device, measured (docs/benchmarks.md): the wide tree
# where its SIMD traversal is compiled in (a CPU with AVX2: wide_traversal.simd_support);
# the binary tree on other CPUs (the lane-by-lane wide traversal ran slower than it, docs/
# architecture.md, "Wide BVH") and on CUDA (an H200 ran the wide one, lane by lane, 10-30x
# slower; CUDA kernels now traverse the binary tree whatever the width, see
# leaf.wide_tree_traversed).
SIMD_WIDTH, PORTABLE_WIDTH = 8, 2
# K of eq. 3.1 per device. CPU: 256 chunks (8,192 triangles); with the paper's 14, two workers
# shared the steps of tasks of a few thousand triangles, whose items had just been written by
# one of them, and spent 25% more in SplitPlane than one worker did alone (4M-triangle
# gallery, two workers: the launch 747 -> 677 ms, 1M 172 -> 158, Conference 44 -> 40, in
# builds interleaved in one process; 1,024 the same as 256). CUDA: 64, where 33,792
# one-thread workers grabbing fewer, larger runs of chunks built Conference 1.5x and the
# 1.1 M-triangle bunny 3x faster on an H200 (docs/benchmarks.md, CUDA sweeps)
BUILD_MIN_CHUNKS = {"cpu": 256, "cuda": 64}
# SAH tasks of at most 1 / (SERIAL_SHARE x workers) of the triangles are partitioned by one
# worker in one pass (build.exchange_in_place), not by the pool's PPS and Swap (two workers:
# every task of at most half the triangles). 1 rather than 4 (builds interleaved in one
# process, medians of 5-10, two workers: 4M gallery 959 -> 938 ms, 1M 232 -> 224,
# Conference 62.7 -> 61.6, dragon 21.0 -> 19.7; 2 and 8 in between and worse)
SERIAL_SHARE = 1
PART_ITEMS = 65536  # fewest triangles worth a launch of their own (prepare, reorder)
REORDER_PARTS = 4  # parts per host thread of the reorder


def default_width(device) -> int:
    return SIMD_WIDTH if simd_support(device)[0] > 0 else PORTABLE_WIDTH


@dataclass
class Bvh:
    vertices: np.ndarray
    indices: np.ndarray
    method: str
    leaf_size: int
    device: wp.context.Device
    arrays: BvhArrays  # device-side view for kernels (the wide nodes too, if any)
    bounds: np.ndarray  # (2, 3) float32
    stats: BvhStats
    mesh: DeviceMesh | None = None  # the mesh on the device, reused by AO and DACRT

    def nodes(self) -> np.ndarray:
        """The node array as a numpy structured array (lo, first, hi, count)."""
        return self.arrays.nodes.numpy()

    def permutation(self) -> np.ndarray:
        """Caller's triangle index of each leaf position."""
        return self.arrays.tri_ids.numpy()


def build_bvh(
    vertices: np.ndarray,
    indices: np.ndarray,
    method: Method = "sah",
    leaf_size: int = 8,
    max_depth: int = STACK_SIZE,
    device=None,
    *,
    min_chunks: int | None = None,
    workers: int | None = None,
    pool_capacity: int | None = None,
    width: Width | None = None,
) -> Bvh:
    """Build a BVH with the task pool in one persistent launch (2012 paper, sec. 4), then
    collapse it into a tree of `width` 4 or 8 (bvh.wide; 2: none; None: the device's
    default, default_width), which `trace` and AO then traverse on CPU (CUDA kernels
    traverse the binary tree). `min_chunks` (K of eq. 3.1) and `workers`: None takes the
    device's (BUILD_MIN_CHUNKS, pool.state.default_workers)."""
    if width is not None and width not in WIDTHS:
        raise ValueError(f"width must be one of {list(WIDTHS)} or None, got {width!r}")
    if method not in METHODS:
        raise ValueError(f"method must be one of {sorted(METHODS)}, got {method!r}")
    if not 1 <= int(leaf_size) <= 64:
        raise ValueError(f"leaf_size must be in 1..64 (8, 16 or 32 are usual), got {leaf_size}")
    if not 1 <= int(max_depth) <= STACK_SIZE:
        raise ValueError(f"max_depth must be in 1..{STACK_SIZE}, got {max_depth}")
    if min_chunks is not None and int(min_chunks) < 1:
        raise ValueError(f"min_chunks must be >= 1, got {min_chunks}")
    device = get_device(device)
    width = default_width(device) if width is None else int(width)
    phase_ms: dict[str, float] = {}
    compile_ms = load_modules(device, *bb.WARP_MODULES, collapse_kernel.module)
    t_total = t0 = time.perf_counter()
    vertices, indices = as_triangle_mesh(vertices, indices)
    phase_ms["validate"] = (time.perf_counter() - t0) * 1e3

    t0 = time.perf_counter()
    m = len(indices)
    mesh = DeviceMesh(vertices, indices, device, validated=True)
    v_wp, f_wp = mesh.v, mesh.f
    threads = (default_workers(device) if workers is None else int(workers)
               ) if device.is_cpu else 1
    # the triangles in parts, one per worker, each with a scene box of its own
    parts = max(1, min(threads, m // PART_ITEMS))

    def fill(b: BuildData) -> tuple[int, np.ndarray]:
        part_bounds = wp.array(np.tile(empty_bounds_numpy(), (parts, 1)), dtype=wp.vec3,
                               device=device)
        flat = wp.zeros(parts, dtype=int, device=device)
        launch_parts(bb.triangle_items, [v_wp, f_wp, 0, 0, part_bounds, flat, b.items], 2, m,
                     parts, threads, device, part_arg=3)
        box = part_bounds.numpy().reshape(parts, 4, 3)
        merged = np.empty((4, 3), np.float32)
        merged[0::2] = box[:, 0::2].min(axis=0)  # lows: of the boxes and of the centroids
        merged[1::2] = box[:, 1::2].max(axis=0)  # highs
        left_out = int(flat.numpy().sum())
        if left_out:
            drop_left_out(b, m, device)
        return m - left_out, merged

    tree = build_items(m, fill, method, leaf_size, max_depth, device,
                       min_chunks=min_chunks, workers=workers, pool_capacity=pool_capacity,
                       phase_ms=phase_ms, start=t0,
                       whole_max=min(int(leaf_size), WHOLE) if device.is_cpu and width > 2
                       else 1)
    n, box, b = tree.count, tree.bounds, tree.data

    t0 = time.perf_counter()
    node_count, depth = tree.node_count, tree.depth
    tri_ids = wp.empty(n, dtype=int, device=device)
    arrays = BvhArrays()
    arrays.nodes = b.nodes if n > 0 else empty_root(device)
    arrays.tri_ids = tri_ids
    arrays.vertices, arrays.indices = v_wp, f_wp
    arrays.tri_verts = wp.empty(1, dtype=wp.vec3, device=device)

    def reorder() -> None:
        # in more parts than threads: while the collapse's serial start holds one host
        # thread, the others take the parts, and it joins them when it is done
        launch_parts(bb.gather_leaf_ids, [b.items, 0, tri_ids], 1, n,
                     max(1, min(REORDER_PARTS * threads, n // PART_ITEMS))
                     if threads > 1 else 1, threads, device)
        release_scratch(b)  # before the collapse allocates the wide tree
        phase_ms["reorder"] = sync_ms(device, t0)

    wide_stats = {"wide_nodes": 0, "wide_stack": 0, "leaf_blocks": 0}
    arrays.blocks = wp.zeros(1, dtype=float, device=device)
    if width > 2 and n > 0:
        # the collapse's serial start runs beside the reorder: "collapse" is what it adds
        arrays.wide, arrays.blocks, wide_stats = collapse(b.nodes, node_count, arrays, n,
                                                          width, device, tree.workers,
                                                          alongside=reorder)
        if wide_stats["wide_stack"] > WIDE_STACK:  # not seen on real scenes: see WIDE_STACK
            width = 2
    else:
        reorder()
        if width > 2:
            arrays.wide = empty_wide(width, device)
            wide_stats["wide_nodes"] = 1
    if width == 2:
        arrays.wide = wp.zeros(1, dtype=float, device=device)
    arrays.width = width
    phase_ms["collapse"] = sync_ms(device, t0 + phase_ms["reorder"] / 1e3)  # after it
    if (width == 2 or not device.is_cpu) and n > 0:  # the binary traversal's leaves
        t0 = time.perf_counter()
        arrays.tri_verts = wp.empty(3 * n, dtype=wp.vec3, device=device)
        fill_leaf_triangles(arrays, n, device, threads)
        phase_ms["leaf triangles"] = sync_ms(device, t0)
    total_ms = (time.perf_counter() - t_total) * 1e3

    node_count = node_count if n > 0 else 1
    nodes = arrays.nodes.numpy()[:node_count]
    # a view of the build's array for 2n - 1 nodes, of which only the pages of these were
    # touched (a copy cost time and took more memory at the peak than it saved)
    arrays.nodes = arrays.nodes[:node_count] if n > 0 else arrays.nodes
    stats = BvhStats(
        action="build", build_ms=total_ms, compile_ms=compile_ms, phase_ms=phase_ms,
        nodes=node_count, leaves=int(np.count_nonzero(nodes["count"])) if n > 0 else 0,
        depth=depth, sah_cost=sah_cost(nodes) if n > 0 else 0.0, triangles=m,
        degenerate=int(m - n), pool_slots_used=int(tree.pool_state[2]),
        pool_steps_published=int(tree.pool_state[3]), workers=tree.workers, method=method,
        leaf_size=int(leaf_size), width=width, **wide_stats, bvh_bytes=tree_bytes(arrays),
        device=str(device))
    return Bvh(vertices=mesh.vertices, indices=mesh.indices, method=method,
               leaf_size=int(leaf_size), device=device, arrays=arrays, bounds=box[:2].copy(),
               stats=stats, mesh=mesh)


def fill_leaf_triangles(arrays: BvhArrays, n: int, device, threads: int) -> None:
    """`arrays.tri_verts` from the mesh in leaf order (bb.leaf_triangles)."""
    launch_claimed(bb.leaf_triangles, n, [arrays.vertices, arrays.indices, arrays.tri_ids,
                                          arrays.tri_verts], device, threads)


def tree_bytes(arrays: BvhArrays) -> int:
    """Bytes of the tree's own arrays (`BvhStats.bvh_bytes`)."""
    return sum(a.capacity for a in (arrays.nodes, arrays.tri_verts, arrays.tri_ids,
                                    arrays.wide, arrays.blocks))


def empty_bounds_numpy() -> np.ndarray:
    """The four boxes the prepare phase's parts widen by atomics (bb.triangle_items): the
    items' box (lo, hi) and their centroids' box (lo, hi), empty; (4, 3) float32."""
    inf = np.float32(np.inf)
    return np.array([[inf] * 3, [-inf] * 3, [inf] * 3, [-inf] * 3], np.float32)


@dataclass
class BoxTree:
    """A binary tree built by the pool over boxes: `data.nodes` (leaves: runs of
    `data.items` in leaf order, whose `tri` is the caller's index of each box) and the
    build's counts."""

    data: BuildData
    count: int  # boxes built (the valid ones)
    node_count: int
    depth: int
    bounds: np.ndarray  # (4, 3) float32: the boxes' box and their centroids' box
    pool_state: np.ndarray
    workers: int


def build_over_boxes(lo: np.ndarray, hi: np.ndarray, keep: np.ndarray, bounds: np.ndarray,
                     method: str, leaf_size: int, max_depth: int, device, *,
                     min_chunks: int | None = None, workers: int | None = None,
                     pool_capacity: int | None = None, phase_ms: dict[str, float],
                     start: float) -> BoxTree:
    """The pool's build (2012 paper, sec. 4) over any boxes: a scene's instance boxes
    (kernels.scene), (N, 3) float32 on the host. Boxes where `keep` is False are left out;
    `bounds` (4, 3) holds the kept boxes' box and their centroids' box. Adds the "prepare"
    phase (from `start`, a perf_counter reading) and the build's phases to `phase_ms`."""

    def fill(b: BuildData) -> tuple[int, np.ndarray]:
        kept = np.flatnonzero(keep)
        items = np.zeros(len(kept), BuildItem.numpy_dtype())
        items["lo"], items["tri"], items["hi"] = lo[kept], kept, hi[kept]
        if len(kept):
            wp.copy(b.items, wp.array(items, dtype=BuildItem, device=device), count=len(kept))
        return len(kept), bounds

    return build_items(len(lo), fill, method, leaf_size, max_depth, device,
                       min_chunks=min_chunks, workers=workers, pool_capacity=pool_capacity,
                       phase_ms=phase_ms, start=start)


def drop_left_out(b: BuildData, count: int, device) -> None:
    """Move the first `count` items but those left out (`tri` -1) to the front of `b.items`,
    in order, through `b.spare`, which changes places with it."""
    kept, offsets = (wp.empty(count, dtype=int, device=device) for _ in range(2))
    wp.launch(bb.kept_items, dim=count, inputs=[b.items, kept], device=device)
    wp.utils.array_scan(kept, offsets, inclusive=False)
    wp.launch(bb.compact_items, dim=count, inputs=[b.items, kept, offsets, b.spare],
              device=device)
    b.items, b.spare = b.spare, b.items


def build_items(count: int, fill: Callable[[BuildData], tuple[int, np.ndarray]], method: str,
                leaf_size: int, max_depth: int, device, *, min_chunks: int | None,
                workers: int | None,
                pool_capacity: int | None, phase_ms: dict[str, float],
                start: float, whole_max: int = 1) -> BoxTree:
    """`build_over_boxes` over `count` boxes that `fill(b)` writes into `b.items`: the ones
    kept, in order from the first position, straight from the triangles in `build_bvh` (no
    box arrays in between); it returns how many it kept and the (4, 3) box of those and of
    their centroids. SAH ranges of at most `whole_max` boxes stay leaves (wide.WHOLE)."""
    workers = default_workers(device) if workers is None else int(workers)
    if min_chunks is None:
        min_chunks = BUILD_MIN_CHUNKS["cpu" if device.is_cpu else "cuda"]
    b = BuildData()
    b.items, b.spare = (wp.empty(max(count, 1), dtype=BuildItem, device=device)
                        for _ in range(2))
    n, box = fill(b) if count else (0, empty_bounds_numpy())

    capacity = pool_capacity or (256 * workers if device.is_cpu else max(4096, 2 * n // leaf_size))
    b.spare_pos, b.scan = (wp.empty(max(n, 1), dtype=int, device=device) for _ in range(2))
    b.mark = wp.empty(max(n, 1), dtype=wp.int8, device=device)
    b.box_lo, b.box_hi, b.cbox_lo, b.cbox_hi = (
        wp.empty(max(n, 1), dtype=wp.vec3, device=device) for _ in range(4)
    )
    bins = (capacity + workers) * int(BINS)  # per slot, then per worker
    b.bin_count = wp.empty(bins, dtype=int, device=device)
    b.bin_lo, b.bin_hi, b.bin_clo, b.bin_chi = (
        wp.empty(bins, dtype=wp.vec3, device=device) for _ in range(4)
    )
    b.tasks = wp.empty(capacity, dtype=BuildTask, device=device)
    b.nodes = wp.empty(max(2 * n - 1, 1), dtype=BvhNode, device=device)
    b.subtree_nodes = wp.empty(workers * int(SUBTREE_NODES), dtype=BvhNode, device=device)
    b.counters = wp.zeros(2, dtype=int, device=device)
    b.phase_cycles = wp.zeros(workers * CYCLE_ROW, dtype=wp.int64, device=device)
    b.worker_bins = capacity
    b.method = METHODS[method]
    b.leaf_size = int(leaf_size)
    b.max_depth = int(max_depth)
    b.whole_max = int(whole_max)
    # tasks small enough that the workers have plenty of others exchange in place (the tree
    # is the same); on CUDA, with thousands of one-thread workers, only those whose steps
    # would run inline anyway
    b.serial_max = max(n // (SERIAL_SHARE * workers), int(CHUNK) * int(min_chunks) - 1)
    pool = make_pool(capacity, workers, int(min_chunks), device)
    wp.launch(bb.reset_bins, dim=bins, inputs=[b], device=device)
    phase_ms["prepare"] = sync_ms(device, start)

    t0 = time.perf_counter()
    if n > 0:
        wp.launch(bb.start_build, dim=1,
                  inputs=[b, pool, *(wp.vec3(*row) for row in box), n], device=device)
        launch_workers(bb.build_worker, workers, [b, pool], device)
    pool_state = check_pool(pool)
    build_ms = sync_ms(device, t0)
    spent = b.phase_cycles.numpy().reshape(workers, -1)[:, : len(PHASE_NAMES)]
    spent = spent.sum(axis=0).astype(np.float64)
    share = spent / spent.sum() if spent.sum() > 0 else np.zeros_like(spent)
    for name, s in zip(PHASE_NAMES, share, strict=True):
        phase_ms[name] = float(build_ms * s)

    node_count, depth = (int(x) for x in b.counters.numpy())
    return BoxTree(data=b, count=n, node_count=node_count, depth=depth, bounds=box,
                   pool_state=pool_state, workers=workers)


def launch_parts(kernel, args: list, first_arg: int, count: int, parts: int, threads: int,
                 device, *, part_arg: int | None = None) -> None:
    """`kernel` over `count` items in `parts` contiguous parts, each a launch of its own,
    taken in turn by `threads` host threads (on CPU a launch runs on one thread):
    argument `first_arg` is set to the part's first item and `part_arg`, if given, to the
    part's number."""
    if count == 0:
        return
    cuts = np.linspace(0, count, parts + 1).astype(int)
    launch = part_launcher(kernel, args, device)

    def run(k: int) -> None:
        changes = {first_arg: int(cuts[k])}
        if part_arg is not None:
            changes[part_arg] = k
        launch(int(cuts[k + 1] - cuts[k]), changes)

    run_parts(run, parts, threads)


def release_scratch(b: BuildData) -> None:
    """Let go of a finished build's arrays except its nodes: the index array (its leaf order
    copied out by the reorder), PPS, Swap, AABB and the bins."""
    b.items = b.spare = b.spare_pos = b.mark = b.scan = None
    b.box_lo = b.box_hi = b.cbox_lo = b.cbox_hi = None
    b.bin_count = b.bin_lo = b.bin_hi = b.bin_clo = b.bin_chi = b.tasks = None


def trace(
    bvh: Bvh,
    origins: np.ndarray,
    directions: np.ndarray,
    tmin: float | np.ndarray = 0.0,
    tmax: float | np.ndarray = np.inf,
    any_hit: bool = False,
    *,
    threads: int | None = None,
    packets: bool = True,
) -> Hits:
    """Closest hit (or, with any_hit, some hit) per ray in [tmin, tmax].

    On CPU the rays are split between `threads` host threads (default: every core), each
    launching its share: a Warp CPU launch runs on one thread. Closest hits of coherent
    runs of 64 rays go as packets, any hits as groups of 64, where `packets_apply` (the same
    hits; False: ray by ray)."""
    origins, directions = as_rays_unread(origins, directions)  # the kernel checks them
    r = len(origins)
    tmin_a, tmax_a = ray_range(tmin, tmax, r, keep_scalar=True)
    device = bvh.device
    t, tri, u, v = (np.empty(r, dt) for dt in (np.float32, np.int32, np.float32, np.float32))
    outputs = [claimed_arg(x, dt, device) for x, dt in ((t, float), (tri, int), (u, float),
                                                         (v, float))]
    inputs = [claimed_arg(origins, wp.vec3, device), claimed_arg(directions, wp.vec3, device),
              claimed_arg(tmin_a, float, device), claimed_arg(tmax_a, float, device)]
    invalid = claimed_arg(np.zeros(1, np.int32), int, device)
    nthreads = host_threads(device, threads)
    kernel = packet_trace_kernel if packets and packets_apply(bvh) else trace_kernel
    launch_claimed(kernel, r, [bvh.arrays, *inputs, int(any_hit), *outputs, invalid], device,
                   nthreads, align=PACKET)
    refuse_flagged_rays(invalid, origins, directions)
    if not device.is_cpu:
        t, tri, u, v = (a.numpy() for a in outputs)
    return Hits(t=t, triangle=tri, u=u, v=v)
