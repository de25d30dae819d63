"""Property-based: hypothesis draws small meshes (random, on an integer grid so that
edges, vertices and coplanar ties are common, or with shared vertices) and rays (many aimed
exactly at vertices and edge midpoints); every engine path must agree with the float64
oracle on hit/miss and t. Failures shrink to a minimal mesh and ray set."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from .cases import check_closest, engine_tracers

TRACERS = engine_tracers()
PROFILE = settings.get_profile("stability")


@st.composite
def scenes(draw):
    """(vertices, indices, origins, directions, tmin, tmax) with coordinates scaled and
    offset as a whole (scale 1e-3 .. 1e3, offset up to 1e3)."""
    grid = draw(st.booleans())
    n_tri = draw(st.integers(1, 24))
    n_vert = draw(st.integers(3, 3 * n_tri))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    if grid:  # small integer grid: exact ties, shared edges, coplanar and degenerate
        v = rng.integers(-3, 4, (n_vert, 3)).astype(np.float64)
    else:
        v = rng.normal(size=(n_vert, 3))
    f = rng.integers(0, n_vert, (n_tri, 3))
    n_ray = draw(st.integers(1, 40))
    lo, hi = v.min(axis=0) - 1, v.max(axis=0) + 1
    o = lo + (hi - lo) * rng.random((n_ray, 3))
    if grid:
        o = np.round(o * 2) / 2  # origins on the half grid: often on planes and edges
    tri = f[rng.integers(0, n_tri, n_ray)]
    w = rng.dirichlet([1, 1, 1], n_ray)
    kind = rng.integers(0, 4, n_ray)
    w[kind == 0] = np.eye(3)[rng.integers(0, 3, int((kind == 0).sum()))]  # a vertex
    w[kind == 1] = [0.5, 0.5, 0.0]  # an edge midpoint
    target = np.einsum("rk,rkj->rj", w, v[tri])
    d = np.where(kind[:, None] == 3, rng.normal(size=(n_ray, 3)), target - o)
    if grid and draw(st.booleans()):  # axis-aligned directions, zero components
        d = np.eye(3)[rng.integers(0, 3, n_ray)] * rng.choice([-1.0, 1.0], (n_ray, 1))
    scale = 10.0 ** draw(st.integers(-3, 3))
    offset = draw(st.sampled_from([0.0, 1.0, 1e2, 1e3]))
    v = (v * scale + offset).astype(np.float32)
    o = (o * scale + offset).astype(np.float32)
    d = (d * scale).astype(np.float32)
    keep = np.any(d != 0, axis=1)
    tmin = np.float32(draw(st.sampled_from([0.0, 0.0, 0.25])))
    tmax = np.float32(draw(st.sampled_from([np.inf, np.inf, 1.0])))
    return v, f.astype(np.int32), o[keep], d[keep], tmin, tmax


@PROFILE
@given(scenes())
def test_engines_agree_with_float64_brute_force(scene):
    """Guards every traversal path against the oracle on inputs no hand-written case
    lists: hit/miss (away from rounding ties), closest t within 2 ulps, any-hit in range."""
    v, f, o, d, tmin, tmax = scene
    if len(o) == 0:
        return
    for name, run in TRACERS.items():
        t, tri = run(v, f, o, d, tmin, tmax)
        check = check_closest(v, f, o, d, t, tri, tmin, tmax)
        assert check.failures == 0, f"{name}: {check.summary()}"
        if name.startswith("bvh"):
            t, tri = run(v, f, o, d, tmin, tmax, any_hit=True)
            check = check_closest(v, f, o, d, t, tri, tmin, tmax, any_hit=True)
            assert check.failures == 0, f"{name} any-hit: {check.summary()}"
