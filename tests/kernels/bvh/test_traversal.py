"""Closest-hit and any-hit traversal against independent references."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh

from scenesort import kernels

from ..reference import (
    assert_same_hits,
    axis_aligned_cube_rays,
    brute_force,
    random_rays,
    random_soup,
)


def embree_closest(vertices, indices, origins, directions):
    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene, vertices, indices)
    res = scene.run(origins, directions, output=1)
    tri = res["primID"].astype(np.int64)
    t = np.where(tri >= 0, res["tfar"], np.inf).astype(np.float32)
    return t, tri


@pytest.mark.parametrize("method", ["sah", "median"])
@pytest.mark.parametrize("leaf_size", [1, 8, 32])
def test_closest_hit_equals_brute_force(method, leaf_size):
    rng = np.random.default_rng(7 + leaf_size)
    v, f = random_soup(rng, 400)
    o, d = random_rays(rng, 600, -0.5, 1.5)
    bvh = kernels.build_bvh(v, f, method=method, leaf_size=leaf_size)
    ref_t, ref_tri = brute_force(v, f, o, d)
    assert_same_hits(kernels.trace(bvh, o, d), ref_t, ref_tri)
    occluded = kernels.trace(bvh, o, d, any_hit=True).triangle >= 0
    assert np.array_equal(occluded, ref_tri >= 0)


def test_per_ray_tmin_tmax_and_any_hit_range():
    rng = np.random.default_rng(11)
    v, f = random_soup(rng, 300)
    o, d = random_rays(rng, 500, -0.5, 1.5)
    tmin = rng.random(500).astype(np.float32) * 0.3
    tmax = tmin + rng.random(500).astype(np.float32)
    bvh = kernels.build_bvh(v, f)
    ref_t, ref_tri = brute_force(v, f, o, d, tmin, tmax)
    hits = kernels.trace(bvh, o, d, tmin=tmin, tmax=tmax)
    assert_same_hits(hits, ref_t, ref_tri)
    anyhit = kernels.trace(bvh, o, d, tmin=tmin, tmax=tmax, any_hit=True)
    assert np.array_equal(anyhit.triangle >= 0, ref_tri >= 0)
    got = anyhit.triangle >= 0
    assert np.all((anyhit.t[got] >= tmin[got]) & (anyhit.t[got] <= tmax[got]))


def test_barycentrics_reconstruct_the_hit_point():
    rng = np.random.default_rng(12)
    v, f = random_soup(rng, 300)
    o, d = random_rays(rng, 500, -0.5, 1.5)
    h = kernels.trace(kernels.build_bvh(v, f), o, d)
    hit = h.triangle >= 0
    tri = v[f[h.triangle[hit]]].astype(np.float64)
    u, w = h.u[hit, None], h.v[hit, None]
    p = (1 - u - w) * tri[:, 0] + u * tri[:, 1] + w * tri[:, 2]
    q = o[hit] + h.t[hit, None] * d[hit].astype(np.float64)
    assert np.abs(p - q).max() < 1e-5


def test_axis_aligned_rays_with_zero_direction_components():
    """A grid of rays along each axis (and with -0.0 components) through a unit-cube mesh."""
    v, f, o, d = axis_aligned_cube_rays()
    h = kernels.trace(kernels.build_bvh(v, f), o, d)
    assert np.all(h.triangle >= 0)
    assert np.all(h.t == 1.5)


def icosphere_rays(subdivisions=3, radius=1.0, offset=(0.0, 0.0, 0.0)):
    """Rays from interior points aimed exactly at every vertex and edge midpoint."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    v = (np.asarray(sphere.vertices) + offset).astype(np.float32)
    f = np.asarray(sphere.faces, np.int32)
    edges = np.asarray(sphere.edges_unique)
    targets = np.vstack([v, (0.5 * (v[edges[:, 0]].astype(np.float64) + v[edges[:, 1]]))])
    centre = np.asarray(offset, np.float64)
    starts = centre + radius * np.array(
        [[0, 0, 0], [0.3, 0.1, -0.2], [-0.5, 0.2, 0.1], [0.05, -0.6, 0.3]]
    )
    o = np.repeat(starts, len(targets), axis=0).astype(np.float32)
    d = (np.tile(targets, (len(starts), 1)) - o).astype(np.float32)
    return v, f, o, d


@pytest.mark.parametrize(
    ("radius", "offset"), [(1.0, 0.0), (1e-3, 0.0), (1e3, 0.0), (1.0, 1e4), (1e3, 1e5)]
)
def test_watertight_closed_mesh_lets_no_ray_escape(radius, offset):
    v, f, o, d = icosphere_rays(3, radius, (offset, -offset, 0.5 * offset))
    for method in ("sah", "median"):
        bvh = kernels.build_bvh(v, f, method=method)
        h = kernels.trace(bvh, o, d)
        assert np.all(h.triangle >= 0), f"{int((h.triangle < 0).sum())} of {len(o)} rays escaped"
        assert np.all(kernels.trace(bvh, o, d, any_hit=True).triangle >= 0)


@pytest.mark.parametrize("name", ["bunny", "sponza", "conference"])
def test_equals_embree_on_shared_scenes(name, shared_scene):
    """Camera rays and random rays: hit/miss identical except for rays that pass within
    float32 rounding of an edge (checked against a float64 brute force), t within 1e-5."""
    scene = shared_scene(name)
    v, f = scene.vertices, scene.indices
    cam = scene.camera
    cam = type(cam).from_dict({**cam.to_dict(), "width": 160, "height": 120})
    o1, d1, _, _ = cam.rays()
    rng = np.random.default_rng(5)
    lo, hi = v.min(axis=0), v.max(axis=0)
    o2 = (lo + (hi - lo) * rng.random((20000, 3))).astype(np.float32)
    d2 = rng.normal(size=(20000, 3)).astype(np.float32)
    o = np.vstack([o1, o2])
    d = np.vstack([d1, d2])
    bvh = kernels.build_bvh(v, f)
    hits = kernels.trace(bvh, o, d)
    ref_t, ref_tri = embree_closest(v, f, o, d)
    mismatch = np.flatnonzero((hits.triangle >= 0) != (ref_tri >= 0))
    assert len(mismatch) <= 1e-4 * len(o)
    for i in mismatch:  # each must be a grazing or edge case decided differently by rounding
        bt, btri = brute_force(v, f, o[i : i + 1], d[i : i + 1])
        if (btri[0] >= 0) != (hits.triangle[i] >= 0):
            pytest.fail(f"ray {i}: ours {hits.triangle[i]}, float64 {btri[0]}, embree {ref_tri[i]}")
    both = (hits.triangle >= 0) & (ref_tri >= 0)
    err = np.abs(hits.t[both] - ref_t[both]) / ref_t[both]
    assert err.max() <= 1e-5
    occluded = kernels.trace(bvh, o, d, any_hit=True).triangle >= 0
    assert np.array_equal(occluded, hits.triangle >= 0)


@pytest.mark.parametrize("any_hit", [False, True])
def test_threads_give_identical_results(any_hit):
    """Whichever host thread claims a chunk of rays, and however small the call."""
    rng = np.random.default_rng(9)
    v, f = random_soup(rng, 2000)
    o, d = random_rays(rng, 50000, -0.5, 1.5)
    bvh = kernels.build_bvh(v, f)
    for n in (1, 100, 50000):
        one = kernels.trace(bvh, o[:n], d[:n], tmax=1.0, any_hit=any_hit, threads=1)
        assert (one.triangle >= 0).any() or n == 1
        for threads in (2, 5):
            many = kernels.trace(bvh, o[:n], d[:n], tmax=1.0, any_hit=any_hit,
                                 threads=threads)
            for name in ("t", "triangle", "u", "v"):
                assert np.array_equal(getattr(one, name), getattr(many, name))


@pytest.mark.parametrize("where", ["bvh", "scene"])
@pytest.mark.parametrize("bad", ["nan origin", "inf direction", "zero direction"])
def test_one_bad_ray_among_many_is_refused_by_the_kernel_that_reads_it(where, bad):
    """The kernels check the rays as they read them (not Python first): one bad ray among
    100k, in any chunk, for closest and any hits, packets or not, on one and two threads,
    gives as_rays's error naming its row; float64 rays go through as_rays itself."""
    v, f = random_soup(np.random.default_rng(3), 200)
    bvh = kernels.build_bvh(v, f)
    target = bvh if where == "bvh" else kernels.build_scene([bvh], [0], np.eye(4)[None, :3])
    o, d = random_rays(np.random.default_rng(4), 100_000)
    good = kernels.trace(target, o, d, threads=2)
    for row in (0, 63_999, 99_999):
        bo, bd = o.copy(), d.copy()
        if bad == "nan origin":
            bo[row, 1] = np.nan
        elif bad == "inf direction":
            bd[row, 2] = -np.inf
        else:
            bd[row] = 0.0
        message = (f"zero-length rows \\(first: row {row}\\)" if bad == "zero direction"
                   else f"NaN or Inf in 1 rows \\(first: row {row}\\)")
        for any_hit, packets, threads in ((False, True, 1), (False, True, 2), (True, True, 2),
                                          (False, False, 2)):
            with pytest.raises(ValueError, match=message):
                kernels.trace(target, bo, bd, any_hit=any_hit, threads=threads,
                              packets=packets)
        with pytest.raises(ValueError, match=message):
            kernels.trace(target, bo.astype(np.float64), bd, threads=2)
    again = kernels.trace(target, o, d, threads=2)  # nothing kept from the refused calls
    assert np.array_equal(again.t, good.t) and np.array_equal(again.triangle, good.triangle)


def test_empty_mesh_and_zero_rays():
    empty = kernels.build_bvh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))
    o, d = random_rays(np.random.default_rng(0), 10)
    h = kernels.trace(empty, o, d)
    assert np.all(h.triangle == -1) and np.all(np.isinf(h.t))
    v, f = random_soup(np.random.default_rng(1), 10)
    h = kernels.trace(kernels.build_bvh(v, f), np.zeros((0, 3), np.float32),
                      np.zeros((0, 3), np.float32))
    assert h.t.shape == (0,)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"directions": np.zeros((4, 3), np.float32)}, "zero-length"),
        ({"origins": np.full((4, 3), np.nan, np.float32)}, "NaN or Inf"),
        ({"directions": np.full((4, 3), np.inf, np.float32)}, "NaN or Inf"),
        ({"origins": np.zeros((3, 3), np.float32)}, "same length"),
        ({"tmax": -1.0}, "tmax must be >= tmin"),
        ({"tmin": np.zeros(3, np.float32)}, "tmin must be a scalar"),
        ({"tmin": np.nan}, "tmin contains NaN"),
    ],
)
def test_bad_rays_are_rejected(kwargs, message):
    v, f = random_soup(np.random.default_rng(2), 10)
    bvh = kernels.build_bvh(v, f)
    args = {"origins": np.zeros((4, 3), np.float32), "directions": np.ones((4, 3), np.float32)}
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        kernels.trace(bvh, **args)
