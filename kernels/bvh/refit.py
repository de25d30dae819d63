"""Refit: a BVH's boxes recomputed bottom-up for moved vertices (same triangles, same tree),
as Embree's and OptiX's refit builds do for meshes whose topology stays (armatures, shape
keys, simulations).

Order of work: the leaf-order triangles (`tri_verts`) from the new vertices, the wide
tree's 4-triangle blocks from them, then the binary nodes and the wide nodes one level at a
time from the deepest up (every level one launch, split between host threads: a node's
children are on the level below, done by the launch before). Unchanged vertices give the
very same boxes (min and max are exact), so a refit of an unmoved mesh is its build.

When to rebuild anyway: the refit tree keeps the old tree's topology, which loosens as the
mesh moves; its SAH cost (traversal and intersection cost 1, over the root's area) is
compared with the cost of the tree as last built, which stands for a fresh build's (the
normalised SAH cost of a fresh build changes little under a smooth deformation: it is
invariant under translation, rotation and uniform scale). Above `REBUILD_RATIO` the mesh is
rebuilt; docs/architecture.md gives the measurement behind the threshold.
"""

from __future__ import annotations

import time

import numpy as np
import warp as wp

from ..core.box import INF, max3, min3
from ..core.launch import host_threads, launch_split, load_modules, sync_ms
from ..core.mesh import DeviceMesh, degenerate_mask
from ..core.validate import as_triangle_mesh
from .api import Bvh, build_bvh
from .build import store_leaf_triangle
from .node import BvhNode, sah_cost
from .wide import BLOCK, BLOCK_WORDS, WORDS_PER_LANE, float_bits

wp.set_module_options({"enable_backward": False, "optimization_level": 3})

# The refit tree's SAH cost over the last build's above which `refit_bvh` rebuilds: measured
# with benchmarks/animation.py --part refit (docs/architecture.md, "Refit").
REBUILD_RATIO = 1.5


@wp.kernel
def refit_triangles(vertices: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.vec3i),
                    tri_ids: wp.array(dtype=int), tri_verts: wp.array(dtype=wp.vec3),
                    positions: wp.array(dtype=int)):
    """Leaf positions `positions` get their triangles' moved vertices."""
    i = positions[wp.tid()]
    store_leaf_triangle(vertices, indices, tri_ids[i], i, tri_verts)


@wp.kernel
def refit_blocks(tri_verts: wp.array(dtype=wp.vec3), blocks: wp.array(dtype=float),
                 block_ids: wp.array(dtype=int)):
    """Each block's 4 lanes from the leaf position stored in its last row (wide.py)."""
    b = block_ids[wp.tid()]
    for k in range(BLOCK):
        base = b * BLOCK_WORDS + k
        i = float_bits(blocks[base + 9 * BLOCK])
        for m in range(3):
            v = tri_verts[3 * i + m]
            for a in range(3):
                blocks[base + (3 * m + a) * BLOCK] = v[a]


@wp.kernel
def refit_binary_level(nodes: wp.array(dtype=BvhNode), tri_verts: wp.array(dtype=wp.vec3),
                       level: wp.array(dtype=int)):
    """A leaf's box from its triangles, an inner node's from its two children (done)."""
    k = level[wp.tid()]
    n = nodes[k]
    lo = wp.vec3(INF)
    hi = wp.vec3(-INF)
    if n.count > 0:
        for j in range(3 * n.first, 3 * (n.first + n.count)):
            lo = min3(lo, tri_verts[j])
            hi = max3(hi, tri_verts[j])
    else:
        left = nodes[n.first]
        right = nodes[n.first + 1]
        lo = min3(left.lo, right.lo)
        hi = max3(left.hi, right.hi)
    n.lo = lo
    n.hi = hi
    nodes[k] = n


@wp.kernel
def refit_wide_level(wide: wp.array(dtype=float), blocks: wp.array(dtype=float), width: int,
                     level: wp.array(dtype=int)):
    """Every used lane of a wide node: a leaf's box from its blocks (padding lanes repeat a
    triangle of the leaf), an inner child's from that child's lanes (a level below)."""
    w = width
    base = level[wp.tid()] * WORDS_PER_LANE * w
    for j in range(w):
        if wide[base + j] != INF:  # an unused lane keeps its point at infinity
            child = float_bits(wide[base + 6 * w + j])
            count = float_bits(wide[base + 7 * w + j])
            lo = wp.vec3(INF)
            hi = wp.vec3(-INF)
            if count > 0:
                for q in range((count + BLOCK - 1) / BLOCK):
                    for r in range(9 * BLOCK):
                        x = blocks[(child + q) * BLOCK_WORDS + r]
                        a = (r / BLOCK) % 3
                        lo[a] = wp.min(lo[a], x)
                        hi[a] = wp.max(hi[a], x)
            else:
                cb = child * WORDS_PER_LANE * w
                for c in range(w):
                    if wide[cb + c] != INF:
                        for a in range(3):
                            lo[a] = wp.min(lo[a], wide[cb + (2 * a) * w + c])
                            hi[a] = wp.max(hi[a], wide[cb + (2 * a + 1) * w + c])
            for a in range(3):
                wide[base + (2 * a) * w + j] = lo[a]
                wide[base + (2 * a + 1) * w + j] = hi[a]


def _levels(first: np.ndarray, inner: np.ndarray, children) -> list[np.ndarray]:
    """Node indices level by level from the root (`children(nodes)` lists the inner ones'
    children), deepest level first."""
    levels = []
    frontier = np.zeros(1, np.int64)
    while len(frontier):
        levels.append(frontier.astype(np.int32))
        frontier = children(frontier[inner[frontier]])
    return levels[::-1]


def _plan(bvh: Bvh) -> dict:
    """What a refit launches, worked out from the tree once and kept on the Bvh."""
    if bvh.refit_plan is None:
        device = bvh.device
        nodes = bvh.nodes()
        first = nodes["first"].astype(np.int64)
        empty = len(bvh.permutation()) == 0  # the empty root is no tree to refit
        binary = [] if empty else _levels(first, nodes["count"] == 0,
                                          lambda f: np.concatenate([first[f], first[f] + 1]))
        plan = {"binary": [wp.array(x, dtype=int, device=device) for x in binary],
                "positions": wp.array(np.arange(len(bvh.permutation()), dtype=np.int32),
                                      dtype=int, device=device),
                "wide": [], "blocks": None}
        w = bvh.arrays.width
        if w > 2 and not empty:
            words = bvh.arrays.wide.numpy().view(np.int32).reshape(-1, int(WORDS_PER_LANE), w)
            lo_x = words[:, 0].view(np.float32)
            inner = (words[:, 7] == 0) & (lo_x != np.inf)  # per node and lane
            child = words[:, 6].astype(np.int64)
            wide = _levels(child, np.ones(len(words), bool),
                           lambda f: child[f][inner[f]])
            plan["wide"] = [wp.array(x, dtype=int, device=device) for x in wide]
            used = bvh.stats.get("leaf_blocks", 0)
            plan["blocks"] = wp.array(np.arange(used, dtype=np.int32), dtype=int, device=device)
        bvh.refit_plan = plan
    return bvh.refit_plan


def refit_bvh(bvh: Bvh, vertices: np.ndarray, *, rebuild_ratio: float = REBUILD_RATIO,
              threads: int | None = None) -> Bvh:
    """The BVH of the same triangles at moved `vertices` ((N, 3), the same N as the build's):
    its boxes refitted in place (the same object is returned, its arrays updated: scenes
    that hold it see the move), or, where the refit tree's SAH cost exceeds `rebuild_ratio`
    times the last build's or a triangle that had no area at the build has one now, a new
    BVH built with the same options. `stats` then says what was done: "action" ("refit" or
    "rebuild"), "sah_ratio" (the refit tree's cost over the build's), "sah_cost",
    "build_sah_cost" (the last build's), "refit_ms" and the refit's "phase_ms"."""
    if not rebuild_ratio > 0:
        raise ValueError(f"rebuild_ratio must be > 0, got {rebuild_ratio!r}")
    device = bvh.device
    compile_ms = load_modules(device, refit_triangles.module)
    t_total = t0 = time.perf_counter()
    phase_ms: dict[str, float] = {}
    if np.shape(vertices) != bvh.vertices.shape:
        raise ValueError(f"vertices must have the build's shape {bvh.vertices.shape} (same "
                         f"mesh, moved), got {np.shape(vertices)}: build a new BVH instead")
    vertices, indices = as_triangle_mesh(vertices, bvh.indices)
    build_cost = float(bvh.stats.get("build_sah_cost", bvh.stats.get("sah_cost", 0.0)))
    gained_area = False
    if bvh.stats.get("degenerate", 0):
        was_flat = np.ones(len(indices), bool)
        was_flat[bvh.permutation()] = False
        gained_area = bool(np.any(was_flat & ~degenerate_mask(vertices, indices, device)))
    mesh = DeviceMesh(vertices, indices, device, validated=True)
    phase_ms["validate"] = sync_ms(device, t0)
    plan = _plan(bvh)
    arrays = bvh.arrays
    nthreads = host_threads(device, threads)

    def run(kernel, shared: list, items: wp.array) -> None:
        launch_split(kernel, items.shape[0], shared, [items], [], [], device, nthreads)

    t0 = time.perf_counter()
    run(refit_triangles, [mesh.v, mesh.f, arrays.tri_ids, arrays.tri_verts], plan["positions"])
    if plan["blocks"] is not None:
        run(refit_blocks, [arrays.tri_verts, arrays.blocks], plan["blocks"])
    phase_ms["triangles"] = sync_ms(device, t0)
    t0 = time.perf_counter()
    for level in plan["binary"]:
        run(refit_binary_level, [arrays.nodes, arrays.tri_verts], level)
    phase_ms["nodes"] = sync_ms(device, t0)
    t0 = time.perf_counter()
    for level in plan["wide"]:
        run(refit_wide_level, [arrays.wide, arrays.blocks, arrays.width], level)
    phase_ms["wide"] = sync_ms(device, t0)
    t0 = time.perf_counter()
    cost = sah_cost(bvh.nodes())
    phase_ms["sah"] = (time.perf_counter() - t0) * 1e3
    ratio = cost / build_cost if build_cost > 0 else 1.0
    box = bvh.nodes()[0]
    bvh.vertices, bvh.mesh = vertices, mesh
    bvh.bounds = np.stack([box["lo"], box["hi"]]).astype(np.float32)
    refit_ms = (time.perf_counter() - t_total) * 1e3
    if ratio > rebuild_ratio or gained_area:
        new = build_bvh(vertices, indices, bvh.method, bvh.leaf_size, device=device,
                        width=bvh.stats.get("width", arrays.width))
        new.stats.update(action="rebuild", sah_ratio=ratio, refit_ms=refit_ms,
                         rebuild_reason="area" if gained_area else "sah")
        return new
    bvh.stats.update(action="refit", sah_ratio=ratio, sah_cost=cost, build_sah_cost=build_cost,
                     refit_ms=refit_ms, phase_ms=phase_ms, compile_ms=compile_ms)
    return bvh
