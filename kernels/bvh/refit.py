"""Refit: a BVH's boxes recomputed bottom-up for moved vertices (same triangles, same tree),
as Embree's and OptiX's refit builds do for meshes whose topology stays (armatures, shape
keys, simulations).

Order of work: the wide tree's 4-triangle blocks from the new vertices (and the binary
traversal's leaf-order triangles, where the tree keeps them; split between host threads),
then the binary nodes and
the wide nodes, each tree in one pass from its last node to its root (children are numbered
after their parents, so they are done first, and memory is read in order), the two trees
side by side on two host threads (they share nothing). One serial pass per tree measured
faster than a launch per level of the tree split between threads (277k triangles: 56 ms
for the binary levels), as the work per node is a few loads. Unchanged vertices give the
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
from dataclasses import replace

import numpy as np
import warp as wp

from ..core.box import INF, max3, min3
from ..core.claim import Claims, claimed_items, launch_claimed
from ..core.compile_options import MODULE_OPTIONS
from ..core.launch import host_threads, load_modules, run_parts, sync_ms
from ..core.mesh import DeviceMesh, degenerate_mask, triangle_corners
from ..core.validate import as_triangle_mesh
from .api import Bvh, build_bvh, fill_leaf_triangles
from .node import BvhArrays
from .wide import (
    BLOCK,
    BLOCK_WORDS,
    ROW_CHILD,
    ROW_COUNT,
    ROW_POSITION,
    WORDS_PER_LANE,
    float_bits,
    store_lane_corners,
)

wp.set_module_options(MODULE_OPTIONS)

# The refit tree's SAH cost over the last build's above which `refit_bvh` rebuilds: between
# the measured ratios where the refit tree's trace and AO time were within the measurement's
# noise of a fresh build's (1.21: 1.01-1.09x; identical trees 0.98-1.08x) and ~15-25% above
# it (1.64: 1.07-1.26x), 1.1 M triangles (benchmarks/animation.py --part refit; docs/
# architecture.md, "Refit").
REBUILD_RATIO = 1.5


@wp.kernel
def refit_blocks(bvh: BvhArrays, claims: Claims):
    """Each block's 4 lanes from the mesh, by the leaf position in its last row (wide.py)."""
    items = claimed_items(claims, wp.tid())
    for b in range(items[0], items[1]):
        for k in range(BLOCK):
            base = b * BLOCK_WORDS + k
            store_lane_corners(bvh, bvh.blocks, base,
                               float_bits(bvh.blocks[base + ROW_POSITION * BLOCK]))


@wp.func
def union_of_lanes(wide: wp.array(dtype=float), node: int, w: int) -> wp.mat33:
    """Rows 0 and 1: the box of a wide node's used lanes."""
    box = wp.mat33(INF, INF, INF, -INF, -INF, -INF, 0.0, 0.0, 0.0)
    base = node * WORDS_PER_LANE * w
    for c in range(w):
        if wide[base + c] != INF:  # an unused lane keeps its point at infinity
            for a in range(3):
                box[0, a] = wp.min(box[0, a], wide[base + (2 * a) * w + c])
                box[1, a] = wp.max(box[1, a], wide[base + (2 * a + 1) * w + c])
    return box


@wp.func
def union_of_blocks(blocks: wp.array(dtype=float), first: int, count: int) -> wp.mat33:
    """Rows 0 and 1: the box of a wide leaf's blocks (padding lanes repeat a triangle of
    the leaf, so every lane counts)."""
    box = wp.mat33(INF, INF, INF, -INF, -INF, -INF, 0.0, 0.0, 0.0)
    for q in range((count + BLOCK - 1) / BLOCK):
        for r in range(ROW_POSITION * BLOCK):  # the coordinate rows
            x = blocks[(first + q) * BLOCK_WORDS + r]
            a = (r / BLOCK) % 3
            box[0, a] = wp.min(box[0, a], x)
            box[1, a] = wp.max(box[1, a], x)
    return box


@wp.func
def lane_box(wide: wp.array(dtype=float), blocks: wp.array(dtype=float), w: int, child: int,
             count: int) -> wp.mat33:
    """A wide lane's box: of its leaf's blocks (count > 0) or of its child's lanes."""
    if count > 0:
        return union_of_blocks(blocks, child, count)
    return union_of_lanes(wide, child, w)


@wp.kernel
def refit_binary(bvh: BvhArrays, count: int, out_sah: wp.array(dtype=wp.float64)):
    """One thread, nodes from the last to the root: a node's children have higher indices
    than it (the build numbers them as it makes them), so they are done first, and memory
    is read in order. A leaf's box from its triangles, an inner node's from its children.
    out_sah[0] gets the SAH sum of `node.sah_cost` (before the division by the root's area,
    which is the caller's)."""
    nodes = bvh.nodes
    total = wp.float64(0.0)
    for k in range(count - 1, -1, -1):
        n = nodes[k]
        lo = wp.vec3(INF)
        hi = wp.vec3(-INF)
        if n.count > 0:
            for i in range(n.first, n.first + n.count):
                t = triangle_corners(bvh.vertices, bvh.indices, bvh.tri_ids[i])
                for m in range(3):
                    lo = min3(lo, t[m])
                    hi = max3(hi, t[m])
        else:
            left = nodes[n.first]
            right = nodes[n.first + 1]
            lo = min3(left.lo, right.lo)
            hi = max3(left.hi, right.hi)
        n.lo = lo
        n.hi = hi
        nodes[k] = n
        e = wp.max(hi - lo, wp.vec3(0.0))
        area = e[0] * e[1] + e[1] * e[2] + e[2] * e[0]  # float32, as sah_cost
        total += wp.float64(area) * wp.float64(wp.max(n.count, 1))
    out_sah[0] = total


@wp.kernel
def refit_wide(wide: wp.array(dtype=float), blocks: wp.array(dtype=float), width: int,
               count: int):
    """One thread, wide nodes from the last to the root (the collapse numbers children
    after parents): every used lane's box, a leaf's from its blocks, an inner child's from
    that child's lanes."""
    w = width
    for k in range(count - 1, -1, -1):
        base = k * WORDS_PER_LANE * w
        for j in range(w):
            if wide[base + j] != INF:
                child = float_bits(wide[base + ROW_CHILD * w + j])
                n = float_bits(wide[base + ROW_COUNT * w + j])
                box = lane_box(wide, blocks, w, child, n)
                for a in range(3):
                    wide[base + (2 * a) * w + j] = box[0, a]
                    wide[base + (2 * a + 1) * w + j] = box[1, a]


def refit_bvh(bvh: Bvh, vertices: np.ndarray, *, rebuild_ratio: float = REBUILD_RATIO,
              threads: int | None = None) -> Bvh:
    """The BVH of the same triangles at moved `vertices` ((N, 3), the same N as the build's):
    its boxes refitted in place (the same object is returned, its arrays updated: scenes
    that hold it see the move), or, where the refit tree's SAH cost exceeds `rebuild_ratio`
    times the last build's or a triangle that had no area at the build has one now, a new
    BVH built with the same options. `stats` (BvhStats) then says what was done: `action`
    ("refit" or "rebuild"), `sah_ratio` (the refit tree's cost over the build's),
    `sah_cost`, `build_sah_cost` (the last build's), `refit_ms` and the refit's
    `phase_ms`."""
    if not rebuild_ratio > 0:
        raise ValueError(f"rebuild_ratio must be > 0, got {rebuild_ratio!r}")
    device = bvh.device
    compile_ms = load_modules(device, refit_blocks.module)
    t_total = t0 = time.perf_counter()
    phase_ms: dict[str, float] = {}
    if np.shape(vertices) != bvh.vertices.shape:
        raise ValueError(f"vertices must have the build's shape {bvh.vertices.shape} (same "
                         f"mesh, moved), got {np.shape(vertices)}: build a new BVH instead")
    vertices, indices = as_triangle_mesh(vertices, bvh.indices)
    last = bvh.stats
    build_cost = last.sah_cost if last.build_sah_cost is None else last.build_sah_cost
    gained_area = False
    if last.degenerate:
        was_flat = np.ones(len(indices), bool)
        was_flat[bvh.permutation()] = False
        gained_area = bool(np.any(was_flat & ~degenerate_mask(vertices, indices, device)))
    mesh = DeviceMesh(vertices, indices, device, validated=True)
    phase_ms["validate"] = sync_ms(device, t0)
    arrays = bvh.arrays
    arrays.vertices, arrays.indices = mesh.v, mesh.f  # what finish_hit and the refit read
    nthreads = host_threads(device, threads)
    triangles = arrays.tri_ids.shape[0]  # 0: the empty root, no tree to refit
    w = arrays.width
    nodes = arrays.nodes.shape[0] if triangles else 0
    wide_nodes = arrays.wide.shape[0] // (int(WORDS_PER_LANE) * w) if w > 2 and triangles else 0

    t0 = time.perf_counter()
    if arrays.tri_verts.shape[0] == 3 * triangles:  # kept for a binary traversal
        fill_leaf_triangles(arrays, triangles, device, nthreads)
    launch_claimed(refit_blocks, bvh.stats.leaf_blocks if w > 2 else 0, [arrays], device,
                   nthreads)
    phase_ms["triangles"] = sync_ms(device, t0)
    t0 = time.perf_counter()
    sah = wp.zeros(1, dtype=wp.float64, device=device)
    trees = [(refit_binary, [arrays, nodes, sah]),
             (refit_wide, [arrays.wide, arrays.blocks, w, wide_nodes])]

    def refit_tree(k: int) -> None:
        wp.launch(trees[k][0], dim=1, inputs=trees[k][1], device=device)

    run_parts(refit_tree, 2, nthreads)
    phase_ms["nodes"] = sync_ms(device, t0)  # both trees
    box = bvh.nodes()[0]
    e = np.maximum(box["hi"] - box["lo"], np.float32(0.0))
    root = float(e[0] * e[1] + e[1] * e[2] + e[2] * e[0])
    cost = float(sah.numpy()[0]) / root if root > 0 else float(nodes)
    ratio = cost / build_cost if build_cost > 0 else 1.0
    bvh.vertices, bvh.mesh = vertices, mesh
    bvh.bounds = np.stack([box["lo"], box["hi"]]).astype(np.float32)
    refit_ms = (time.perf_counter() - t_total) * 1e3
    if ratio > rebuild_ratio or gained_area:
        new = build_bvh(vertices, indices, bvh.method, bvh.leaf_size, device=device,
                        width=last.width)
        new.stats = replace(new.stats, action="rebuild", sah_ratio=ratio, refit_ms=refit_ms,
                            rebuild_reason="area" if gained_area else "sah")
        return new
    bvh.stats = replace(last, action="refit", sah_ratio=ratio, sah_cost=cost,
                        build_sah_cost=build_cost, refit_ms=refit_ms, phase_ms=phase_ms,
                        compile_ms=compile_ms)
    return bvh
