"""Extreme sizes: no triangles, one triangle, two million triangles; zero, one and ten
million rays. Sizes are where index arithmetic overflows, thread splits go wrong and an
empty tree is entered by every ray."""

from __future__ import annotations

import numpy as np
import pytest

from scenesort import kernels

from .cases import box_room, check_closest, check_escapes, icosphere

EMPTY = (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))


def test_empty_mesh_misses_every_query():
    """Guards the empty tree beyond test_trace.py's closest-hit case: any-hit, finite and
    infinite ranges, axis-aligned rays through the origin (the empty root's box must not
    look like all of space) and AO (every pixel 1.0, as for a miss)."""
    bvh = kernels.build_bvh(*EMPTY)
    o = np.array([[0, 0, 0], [1, 2, 3], [-1, 0, 0], [0, 0, 0]], np.float32)
    d = np.array([[1, 0, 0], [0, 0, -1], [1, 1, 1], [-0.0, 1, 0]], np.float32)
    for any_hit in (False, True):
        for tmin in (0.0, -np.inf):
            h = kernels.trace(bvh, o, d, tmin=tmin, any_hit=any_hit)
            assert np.all(h.triangle == -1) and np.all(np.isinf(h.t))
    assert np.all(kernels.ambient_occlusion(bvh, o, d, spp=4) == 1.0)


def test_vertices_without_triangles_and_zero_rays():
    """Guards the other empty shapes: vertices but no triangles builds the empty tree, and
    zero rays give empty (0,) results from trace, any-hit and AO."""
    v = np.random.default_rng(0).random((10, 3)).astype(np.float32)
    bvh = kernels.build_bvh(v, np.zeros((0, 3), np.int32))
    assert bvh.stats.triangles == 0 and bvh.stats.leaves == 0
    z = np.zeros((0, 3), np.float32)
    full = kernels.build_bvh(*box_room(2))
    for b in (bvh, full):
        for any_hit in (False, True):
            h = kernels.trace(b, z, z, any_hit=any_hit)
            assert h.t.shape == h.triangle.shape == h.u.shape == (0,)
        assert kernels.ambient_occlusion(b, z, z).shape == (0,)


def test_one_ray_and_one_triangle():
    """Guards the smallest non-empty case (one launch item, root is a leaf), with and
    without a per-ray range array of length 1."""
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    bvh = kernels.build_bvh(v, np.array([[0, 1, 2]], np.int32))
    o = np.array([[0.2, 0.2, 1]], np.float32)
    d = np.array([[0, 0, -1]], np.float32)
    h = kernels.trace(bvh, o, d)
    assert h.triangle.tolist() == [0] and h.t.tolist() == [1.0]
    assert np.isclose(h.u[0], 0.2) and np.isclose(h.v[0], 0.2)
    h = kernels.trace(bvh, o, d, tmin=np.array([1.5], np.float32))
    assert h.triangle.tolist() == [-1]


@pytest.mark.slow
def test_two_million_triangles():
    """Guards index and node-count arithmetic at 2M triangles (4M nodes, 6M vertices):
    an icosphere of 1.31M triangles inside a 0.7M-triangle soup far outside. Rays from
    inside the sphere must all hit it (none escape) at the float64 t of their triangle."""
    sv, sf = icosphere(8)
    rng = np.random.default_rng(1)
    soup = (rng.uniform(-1, 1, (700_000, 1, 3)) * 50 + rng.normal(size=(700_000, 3, 3)))
    soup = soup[np.linalg.norm(soup.mean(axis=1), axis=1) > 5].reshape(-1, 3)
    v = np.vstack([sv, soup]).astype(np.float32)
    f = np.vstack([sf, len(sv) + np.arange(len(soup)).reshape(-1, 3)]).astype(np.int32)
    assert len(f) >= 1_990_000
    bvh = kernels.build_bvh(v, f)
    assert bvh.stats.triangles == len(f) and bvh.stats.degenerate == 0
    perm = bvh.permutation()
    assert len(perm) == len(f) and np.array_equal(np.bincount(perm, minlength=len(f)),
                                                  np.ones(len(f), np.int64))
    o = (rng.uniform(-0.5, 0.5, (20_000, 3))).astype(np.float32)
    d = rng.normal(size=(20_000, 3)).astype(np.float32)
    h = kernels.trace(bvh, o, d)
    check = check_escapes(v, f, o, d, h.t, h.triangle)
    assert check.failures == 0, check.summary()
    assert np.all(h.triangle < len(sf))  # the sphere, never the soup behind it


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_ten_million_rays():
    """Guards ray-count arithmetic and the per-thread split at 10M rays (120 MB of rays):
    every ray from inside a closed room hits, and a sample agrees with the float64 oracle."""
    v, f = box_room(4)
    v = v.astype(np.float32)
    n = 10_000_000
    rng = np.random.default_rng(2)
    o = (rng.uniform(-0.9, 0.9, (n, 3)) * [1, 0.5, 0.7]).astype(np.float32)
    d = rng.normal(size=(n, 3)).astype(np.float32)
    h = kernels.trace(kernels.build_bvh(v, f), o, d)
    assert h.t.shape == (n,)
    assert np.all(h.triangle >= 0), f"{int((h.triangle < 0).sum())} escaped"
    sample = np.r_[0:2000, n - 2000 : n, rng.integers(0, n, 4000)]
    check = check_closest(v, f, o[sample], d[sample], h.t[sample], h.triangle[sample])
    assert check.failures == 0, check.summary()
