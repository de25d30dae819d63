"""Divide-and-conquer ray tracing (`kernels.dacrt_trace`, both variants) against the BVH
tracer and brute force; task-pool specifics (splits, workers, pool errors)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from scenesort.kernels import DacrtStats, dacrt_trace

from scenesort import kernels

from ..reference import (
    assert_same_hits,
    axis_aligned_cube_rays,
    brute_force,
    random_rays,
    random_soup,
)

VARIANTS = [("pool", "rdh"), ("pool", "median"), ("breadth_first", "rdh")]
# small tests have few rays: let RDH sample every task with 16 rays or more (default 4096),
# and let tasks of over 64 rays + triangles run the paper's PPS/Swap phases (default on
# CPU: a worker's share of all of them),
# so that both sorting paths run in every test
SMALL = {"rdh_min_rays": 16, "small_items": 64}


def bvh_hits(v, f, o, d, tmin=0.0, tmax=np.inf):
    return kernels.trace(kernels.build_bvh(v, f), o, d, tmin=tmin, tmax=tmax)


def assert_equal_hits(ours, ref):
    assert_same_hits(ours, ref.t, ref.triangle)
    hit = ours.triangle >= 0
    same = hit & (ours.triangle == ref.triangle)
    assert np.allclose(ours.u[same], ref.u[same], atol=1e-6)
    assert np.allclose(ours.v[same], ref.v[same], atol=1e-6)


@pytest.mark.parametrize("split", ["median", "rdh"])
def test_counting_sort_of_small_tasks_equals_the_pps_rounds(split):
    """small_items=0: every task sorts with PPS/Swap; huge: every task with the one-worker
    counting sort. Both give the BVH's hits; with the median, the same task tree too (RDH
    samples items by position, and the two sorts order items within a class differently)."""
    rng = np.random.default_rng(11)
    v, f = random_soup(rng, 2000)
    o, d = random_rays(rng, 3000, -0.5, 1.5)
    ref = bvh_hits(v, f, o, d)
    stats = []
    for small in (0, 1 << 30):
        info = DacrtStats()
        hits = dacrt_trace(v, f, o, d, split=split, stats=info,
                           **{**SMALL, "small_items": small})
        assert_equal_hits(hits, ref)
        assert (info.phase_ms["Sort"] > 0) == (small > 0)
        assert (info.phase_ms["PPS1"] > 0) == (small == 0)
        stats.append(info)
    tree = ("tasks", "intersection_tasks", "rays_sorted", "tris_sorted", "pairs")
    if split == "median":
        for key in tree:
            assert getattr(stats[0], key) == getattr(stats[1], key), key
    else:  # each sort's tree is its own, and RDH's: neither is the median's
        median = DacrtStats()
        dacrt_trace(v, f, o, d, split="median", stats=median, **SMALL)
        for info in stats:
            assert [getattr(info, k) for k in tree] != [getattr(median, k) for k in tree]


def camera_rays(scene, width: int = 64, height: int = 48):
    """The scene's own camera at a small resolution (same 4:3 aspect)."""
    return dataclasses.replace(scene.camera, width=width, height=height).rays()


@pytest.mark.parametrize(("variant", "split"), VARIANTS)
@pytest.mark.parametrize(("triangles", "rays"), [(1, 50), (40, 300), (3000, 6000)])
def test_equals_bvh_on_random_soups(variant, split, triangles, rays):
    rng = np.random.default_rng(triangles + rays)
    v, f = random_soup(rng, triangles)
    o, d = random_rays(rng, rays, -0.5, 1.5)
    h = dacrt_trace(v, f, o, d, variant=variant, split=split, alpha=16, beta=16,
                    **SMALL)
    assert_equal_hits(h, bvh_hits(v, f, o, d))


@pytest.mark.parametrize(("variant", "split"), VARIANTS)
def test_per_ray_range_and_shared_vertices(variant, split):
    """Per-ray tmin/tmax, and a mesh with shared (even repeated) vertices on a coarse grid,
    so that split planes fall exactly on triangle edges."""
    rng = np.random.default_rng(5)
    v, f = random_soup(rng, 2000, vertices=400)
    v = np.floor(v * 8).astype(np.float32)
    o, d = random_rays(rng, 3000, -1.0, 9.0)
    tmin = (rng.random(3000) * 2).astype(np.float32)
    tmax = tmin + (rng.random(3000) * 8).astype(np.float32)
    h = dacrt_trace(v, f, o, d, tmin, tmax, variant=variant, split=split, alpha=8, beta=8,
                    **SMALL)
    assert_equal_hits(h, bvh_hits(v, f, o, d, tmin, tmax))


@pytest.mark.parametrize("variant", ["pool", "breadth_first"])
def test_axis_aligned_rays_and_closed_mesh(variant):
    """Rays with -0.0 and 0 direction components along each axis through a cube, and rays
    from inside a closed icosphere to its vertices: none may escape."""
    v, f, o, d = axis_aligned_cube_rays()
    h = dacrt_trace(v, f, o, d, variant=variant, alpha=1, beta=1)
    assert np.all(h.triangle >= 0) and np.all(h.t == 1.5)
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1e3)
    v = (np.asarray(sphere.vertices) + 1e4).astype(np.float32)
    f = np.asarray(sphere.faces, np.int32)
    o = np.repeat(np.array([[1e4 + 100, 1e4 - 200, 1e4 + 50]], np.float32), len(v), axis=0)
    h = dacrt_trace(v, f, o, v - o, variant=variant, alpha=8, beta=8)
    assert np.all(h.triangle >= 0), f"{int((h.triangle < 0).sum())} rays escaped"


def rays_from_surface_points(n: int, seed: int):
    """An icosphere and n rays through random points on its triangles (float64 barycentric
    points, random unit directions): (v, f, points, directions)."""
    sphere = trimesh.creation.icosphere(subdivisions=3)
    v = np.asarray(sphere.vertices, np.float32)
    f = np.asarray(sphere.faces, np.int32)
    rng = np.random.default_rng(seed)
    w = rng.dirichlet([1.0, 1.0, 1.0], n)
    p = np.einsum("ni,nij->nj", w, v.astype(np.float64)[f[rng.integers(0, len(f), n)]])
    d = rng.normal(size=(n, 3))
    return v, f, p, d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.parametrize("variant", ["pool", "breadth_first"])
@pytest.mark.parametrize(("tmin", "tmax"), [(0.0, np.inf), (0.25, np.inf), (0.0, 0.25)],
                         ids=["tmin=0", "tmin>0", "tmax"])
def test_refined_distances_stay_in_the_ray_range(variant, tmin, tmax):
    """Rays whose range starts (or ends) exactly on a triangle: the float32 test accepts a
    hit at t within rounding of tmin (tmax), and the float64 refinement of t may then fall
    just outside [tmin, tmax]; it is clamped to the range the float32 test accepted, as
    `trace` does. (Before the fix, of 20,000 rays starting on the icosphere with tmin = 0,
    238 got t < 0 from both variants, none from `trace`.)"""
    v, f, p, d = rays_from_surface_points(20_000, seed=0)
    anchor = tmin if tmin > 0 else (tmax if np.isfinite(tmax) else 0.0)
    o = (p - anchor * d).astype(np.float32)
    d = d.astype(np.float32)
    ref = bvh_hits(v, f, o, d, tmin, tmax)
    ours = dacrt_trace(v, f, o, d, tmin, tmax, variant=variant)
    for h in (ours, ref):
        hit = h.triangle >= 0
        assert hit.mean() > 0.5
        assert np.all(h.t[hit] >= np.float32(tmin)), f"{int((h.t[hit] < tmin).sum())} < tmin"
        assert np.all(h.t[hit] <= np.float32(tmax)), f"{int((h.t[hit] > tmax).sum())} > tmax"
    assert_equal_hits(ours, ref)


@pytest.mark.parametrize("name", ["bunny", "dragon", "buddha", "blade"])
def test_equals_bvh_on_shared_objects(name, shared_scene):
    scene = shared_scene(name)
    o, d, tmin, tmax = camera_rays(scene)
    ref = bvh_hits(scene.vertices, scene.indices, o, d, tmin, tmax)
    assert (ref.triangle >= 0).mean() > 0.05
    for variant, split in VARIANTS:
        h = dacrt_trace(scene.vertices, scene.indices, o, d, tmin, tmax, variant=variant,
                        split=split, **SMALL)
        assert_equal_hits(h, ref)


@pytest.mark.parametrize("name", ["sponza", "sibenik", "conference"])
def test_equals_bvh_with_camera_inside(name, shared_scene):
    """Indoor cameras: every ray starts inside the scene box (the hard case for DACRT)."""
    scene = shared_scene(name)
    o, d, tmin, tmax = camera_rays(scene)
    lo, hi = scene.vertices.min(axis=0), scene.vertices.max(axis=0)
    assert np.all((o >= lo) & (o <= hi))
    ref = bvh_hits(scene.vertices, scene.indices, o, d, tmin, tmax)
    assert (ref.triangle >= 0).mean() > 0.9
    for variant, split in VARIANTS:
        stats = DacrtStats()
        h = dacrt_trace(scene.vertices, scene.indices, o, d, tmin, tmax, variant=variant,
                        split=split, stats=stats, **SMALL)
        assert_equal_hits(h, ref)
        assert stats.peak_bytes > o.nbytes + d.nbytes + scene.vertices.nbytes


@pytest.mark.parametrize("variant", ["pool", "breadth_first"])
def test_degenerate_triangles_never_hit_and_empty_inputs(variant):
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0]], np.float32)
    f = np.array([[0, 1, 3], [0, 1, 2]], np.int32)  # the first is a zero-area sliver
    o = np.array([[0.5, 0.0, 1.0], [0.2, 0.2, 1.0]], np.float32)
    d = np.array([[0, 0, -1], [0, 0, -1]], np.float32)
    h = dacrt_trace(v, f, o, d, variant=variant)
    assert list(h.triangle) == [1, 1]
    empty = dacrt_trace(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), o, d,
                        variant=variant)
    assert np.all(empty.triangle == -1) and np.all(np.isinf(empty.t))
    none = dacrt_trace(v, f, np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32),
                       variant=variant)
    assert none.t.shape == (0,)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"directions": np.zeros((4, 3), np.float32)}, "zero-length"),
        ({"origins": np.full((4, 3), np.nan, np.float32)}, "NaN or Inf"),
        ({"origins": np.zeros((3, 3), np.float32)}, "same length"),
        ({"tmax": -1.0}, "tmax must be >= tmin"),
        ({"tmin": np.nan}, "tmin contains NaN"),
        ({"indices": np.array([[0, 1, 99]])}, "indices must lie in"),
        ({"vertices": np.zeros((3, 2), np.float32)}, "vertices must have shape"),
        ({"variant": "depth_first"}, "variant must be one of"),
        ({"split": "sah"}, "split must be one of"),
        ({"max_depth": 0}, "max_depth"),
    ],
)
def test_bad_input_is_rejected_like_build_bvh(kwargs, message):
    v, f = random_soup(np.random.default_rng(2), 10)
    args = {"vertices": v, "indices": f, "origins": np.zeros((4, 3), np.float32),
            "directions": np.ones((4, 3), np.float32)}
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        dacrt_trace(**args)


def test_pool_workers_and_splits_agree_and_report_phases():
    rng = np.random.default_rng(9)
    v, f = random_soup(rng, 4000)
    o, d = random_rays(rng, 8000, -0.5, 1.5)
    runs = []
    for workers in (1, 2):
        for split in ("median", "rdh"):
            stats = DacrtStats()
            runs.append(dacrt_trace(v, f, o, d, split=split, workers=workers, stats=stats,
                                    **SMALL))
            assert set(stats.phase_ms) == {"SplitPlane", "PPS1", "Swap1", "PPS2", "Swap2",
                                              "AABB", "Intersect", "Sort", "Children"}
            assert stats.phase_ms["Children"] > 0
            assert (stats.phase_ms["SplitPlane"] > 0) == (split == "rdh")
            assert stats.tasks > 7 and stats.intersection_tasks > 1
            # the root task alone sorts every ray and every triangle once
            assert stats.rays_sorted >= len(o) and stats.tris_sorted >= len(f)
            # a ray with a hit was tested in at least one intersection task
            tested = stats.intersection_rays - stats.intersection_rays_skipped
            assert tested >= np.count_nonzero(runs[-1].triangle >= 0) > 0
            assert stats.intersection_rays_skipped > 0
    for h in runs[1:]:  # the closest hit with the (t, triangle) tie rule is deterministic
        assert np.array_equal(h.triangle, runs[0].triangle)
        assert np.array_equal(h.t, runs[0].t)


def test_pool_overflow_raises_pool_error():
    rng = np.random.default_rng(3)
    v, f = random_soup(rng, 3000)
    o, d = random_rays(rng, 3000, -0.5, 1.5)
    with pytest.raises(kernels.PoolError, match="overflow"):
        dacrt_trace(v, f, o, d, pool_capacity=3, workers=1)


def test_default_pool_grows_after_an_overflow(monkeypatch):
    """With pool_capacity=None an overflow is not the caller's problem: the trace runs
    again with a bigger pool and gives the BVH's hits."""
    import scenesort.kernels.dacrt.api as api

    monkeypatch.setattr(api, "POOL_SLOTS", 3)
    rng = np.random.default_rng(3)
    v, f = random_soup(rng, 3000)
    o, d = random_rays(rng, 3000, -0.5, 1.5)
    stats = DacrtStats()
    hits = dacrt_trace(v, f, o, d, workers=1, stats=stats, **SMALL)
    assert stats.pool_retries >= 1 and stats.pool_capacity == 3 * 4 ** stats.pool_retries
    assert_equal_hits(hits, bvh_hits(v, f, o, d))


@settings(max_examples=20, deadline=None)
@given(
    triangles=st.integers(1, 200),
    rays=st.integers(1, 200),
    seed=st.integers(0, 2**32 - 1),
    grid=st.sampled_from([None, 4]),
    variant=st.sampled_from(VARIANTS),
)
def test_dacrt_equals_bvh_equals_brute_force(triangles, rays, seed, grid, variant):
    rng = np.random.default_rng(seed)
    v, f = random_soup(rng, triangles)
    if grid:
        v = np.floor(v * grid).astype(np.float32)
    o, d = random_rays(rng, rays, -0.5, 1.5)
    ref = bvh_hits(v, f, o, d)
    ref_t, ref_tri = brute_force(v, f, o, d)
    assert_same_hits(ref, ref_t, ref_tri, rel=1e-5)
    h = dacrt_trace(v, f, o, d, variant=variant[0], split=variant[1], alpha=4, beta=4, **SMALL)
    assert_equal_hits(h, ref)
    assert_same_hits(h, ref_t, ref_tri, rel=1e-5)
