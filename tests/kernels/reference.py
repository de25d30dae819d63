"""Independent references for the engine tests: float64 brute force and exact BVH checks."""

from __future__ import annotations

import numpy as np


def brute_force(vertices, indices, origins, directions, tmin=0.0, tmax=np.inf):
    """Closest hit per ray by float64 Moller-Trumbore over every triangle: (t, triangle)."""
    v = vertices.astype(np.float64)
    v0 = v[indices[:, 0]]
    e1 = v[indices[:, 1]] - v0
    e2 = v[indices[:, 2]] - v0
    r = len(origins)
    tmin = np.broadcast_to(np.asarray(tmin, np.float64), (r,))
    tmax = np.broadcast_to(np.asarray(tmax, np.float64), (r,))
    best_t = np.full(r, np.inf)
    best_tri = np.full(r, -1)
    for i in range(r):
        o = origins[i].astype(np.float64)
        d = directions[i].astype(np.float64)
        p = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, p)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            s = o - v0
            u = np.einsum("ij,ij->i", s, p) * inv
            q = np.cross(s, e1)
            w = (q @ d) * inv
            t = np.einsum("ij,ij->i", e2, q) * inv
            ok = (det != 0) & (u >= 0) & (w >= 0) & (u + w <= 1) & (t >= tmin[i]) & (t <= tmax[i])
        if ok.any():
            j = int(np.argmin(np.where(ok, t, np.inf)))
            best_t[i] = t[j]
            best_tri[i] = j
    return best_t, best_tri


def degenerate_triangles(vertices, indices) -> np.ndarray:
    """Mask of zero-area triangles: the float64 cross product of the float32 edges is zero."""
    v = vertices.astype(np.float64)
    a, b, c = v[indices[:, 0]], v[indices[:, 1]], v[indices[:, 2]]
    return ~np.any(np.cross(b - a, c - a) != 0.0, axis=1)


def check_bvh(bvh, leaf_size: int, max_depth: int = 64) -> None:
    """Exact structure: every non-degenerate triangle in exactly one leaf, leaf sizes kept
    (except at the depth cap), every box tight around its triangles and its children."""
    nodes = bvh.nodes()
    perm = bvh.permutation()
    v, f = bvh.vertices, bvh.indices
    e1 = v[f[:, 1]].astype(np.float64) - v[f[:, 0]]
    e2 = v[f[:, 2]].astype(np.float64) - v[f[:, 0]]
    valid = np.flatnonzero(np.any(np.cross(e1, e2) != 0, axis=1))
    assert np.array_equal(np.sort(perm), valid), "leaf order is not a permutation of the triangles"
    if len(valid) == 0:
        return
    tri = v[f[perm]]  # (n, 3, 3) in leaf order
    tri_lo, tri_hi = tri.min(axis=1), tri.max(axis=1)
    covered = np.zeros(len(perm), dtype=np.int64)
    seen = np.zeros(len(nodes), dtype=bool)
    stack = [(0, 0)]
    max_seen = 0
    while stack:
        i, depth = stack.pop()
        assert not seen[i], f"node {i} reached twice"
        seen[i] = True
        max_seen = max(max_seen, depth)
        node = nodes[i]
        lo, hi = node["lo"], node["hi"]
        if node["count"] > 0:
            a, n = int(node["first"]), int(node["count"])
            assert n <= leaf_size or depth == max_depth - 1, f"leaf {i} holds {n} > {leaf_size}"
            covered[a : a + n] += 1
            assert np.array_equal(lo, tri_lo[a : a + n].min(axis=0)), f"leaf {i} box not tight"
            assert np.array_equal(hi, tri_hi[a : a + n].max(axis=0)), f"leaf {i} box not tight"
        else:
            c = int(node["first"])
            assert c > 0 and c + 1 < len(nodes), f"node {i} has children {c}, {c + 1}"
            kids = nodes[[c, c + 1]]
            assert np.array_equal(lo, np.minimum(kids["lo"][0], kids["lo"][1])), f"node {i} box"
            assert np.array_equal(hi, np.maximum(kids["hi"][0], kids["hi"][1])), f"node {i} box"
            stack += [(c, depth + 1), (c + 1, depth + 1)]
    assert seen.all(), f"{int((~seen).sum())} nodes are not reachable from the root"
    assert np.all(covered == 1), "a triangle position is in no leaf or in several"
    assert bvh.stats.depth == max_seen
    assert bvh.stats.nodes == len(nodes)
    assert bvh.stats.leaves == int(np.count_nonzero(nodes["count"]))


def random_soup(rng, triangles: int, vertices: int | None = None):
    """A random triangle soup in the unit cube: separate vertices per triangle, or shared
    ones picked at random (which may repeat within a triangle) when `vertices` is given."""
    if vertices is None:
        v = rng.random((3 * triangles, 3)).astype(np.float32)
        return v, rng.permutation(3 * triangles).reshape(triangles, 3).astype(np.int32)
    v = rng.random((vertices, 3)).astype(np.float32)
    return v, rng.integers(0, vertices, (triangles, 3)).astype(np.int32)


def random_rays(rng, count: int, lo=0.0, hi=1.0):
    o = (lo + (hi - lo) * rng.random((count, 3))).astype(np.float32)
    d = rng.normal(size=(count, 3)).astype(np.float32)
    return o, d


def axis_aligned_cube_rays():
    """A unit cube mesh and a 7x7 grid of rays along each axis, both ways, whose other two
    direction components are -0.0 (or 0.0): every ray hits at t = 1.5."""
    import trimesh

    box = trimesh.creation.box(extents=(1, 1, 1))
    g = np.linspace(-0.45, 0.45, 7, dtype=np.float32)
    a, b = np.meshgrid(g, g)
    origins, directions = [], []
    for axis in range(3):
        for sign in (1.0, -1.0):
            o = np.zeros((a.size, 3), np.float32)
            o[:, (axis + 1) % 3] = a.ravel()
            o[:, (axis + 2) % 3] = b.ravel()
            o[:, axis] = -2.0 * sign
            d = np.full((a.size, 3), -0.0, np.float32)
            d[:, axis] = sign
            origins.append(o)
            directions.append(d)
    return (np.asarray(box.vertices, np.float32), np.asarray(box.faces, np.int32),
            np.vstack(origins), np.vstack(directions))


def assert_same_hits(hits, ref_t, ref_tri, rel=1e-6):
    """Hit/miss identical; t within `rel`; a different triangle only where t is equal."""
    ours = hits.triangle >= 0
    theirs = ref_tri >= 0
    assert np.array_equal(ours, theirs), f"{int((ours != theirs).sum())} hit/miss mismatches"
    both = ours & theirs
    err = np.abs(hits.t[both] - ref_t[both]) / np.maximum(np.abs(ref_t[both]), 1e-30)
    assert err.max(initial=0) <= rel, f"t differs by {err.max():.3g} relative"
    other = both & (hits.triangle != ref_tri)
    assert np.all(np.abs(hits.t[other] - ref_t[other]) <= rel * np.abs(ref_t[other]))
