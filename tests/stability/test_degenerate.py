"""Degenerate geometry: zero-area, collinear, coincident and duplicated triangles,
coplanar overlaps and extreme size ratios. Degenerate triangles never hit and never break
the build; everything else traces as the float64 oracle says."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from scenesort import kernels
from tests.kernels.reference import check_bvh

from .cases import check_closest, huge_over_tiny, mixed_scene, plane_grid, scene_rays


def degenerate_soup():
    """Zero-area triangles of every kind on the x axis and the plane z = 0: repeated
    vertex, three distinct collinear points, all three coincident, plus a needle whose
    area is exactly zero only in float64 of its float32 coordinates."""
    v = np.array([
        [0, 0, 0], [1, 0, 0], [2, 0, 0], [0.5, 0, 0],  # collinear on the x axis
        [0, 1, 0], [1, 1, 0],  # z = 0 plane
        [0.25, 0.25, 0],  # coincident point (used three times)
        [3, 3, 0], [3, 3, 0],  # two equal vertices (distinct indices)
    ], np.float32)
    f = np.array([
        [0, 1, 2],  # collinear, distinct
        [0, 3, 1],  # collinear, distinct, middle vertex inside
        [0, 0, 4],  # repeated index
        [7, 8, 5],  # equal coordinates, different indices
        [6, 6, 6],  # all coincident
        [4, 5, 4],  # repeated index, other order
    ], np.int32)
    return v, f


@pytest.mark.parametrize("method", ["sah", "median"])
@pytest.mark.parametrize("leaf_size", [1, 8])
def test_degenerate_triangles_are_skipped_and_never_hit(method, leaf_size):
    """Guards the build against zero-area triangles (a zero-extent box or NaN in a split)
    and the trace against hitting them: rays aimed exactly at their points and along the
    lines they collapse to must all miss."""
    v, f = degenerate_soup()
    bvh = kernels.build_bvh(v, f, method=method, leaf_size=leaf_size)
    assert bvh.stats.degenerate == len(f)
    check_bvh(bvh, leaf_size)
    targets = np.vstack([v, [[0.7, 0, 0], [1.5, 0, 0], [0, 0.5, 0], [3, 2, 0]]])
    o = np.tile(np.array([[0.3, 0.4, 1.0]], np.float32), (len(targets), 1))
    d = (targets - o).astype(np.float32)
    o = np.vstack([o, [[-1, 0, 0], [0.25, 0.25, 5], [3, 3, -1]]]).astype(np.float32)
    d = np.vstack([d, [[1, 0, 0], [0, 0, -1], [0, 0, 1]]]).astype(np.float32)
    for any_hit in (False, True):
        h = kernels.trace(bvh, o, d, any_hit=any_hit)
        assert np.all(h.triangle == -1) and np.all(np.isinf(h.t))


def test_degenerate_triangles_mixed_into_a_real_scene():
    """Guards against degenerate triangles corrupting the leaves they share with real
    ones: the scene with a degenerate copy of every tenth triangle (collapsed onto an
    edge) must trace exactly like the float64 oracle on the real triangles."""
    v, f = mixed_scene(2)
    bad = f[::10].copy()
    bad[:, 2] = bad[:, 1]
    rng = np.random.default_rng(0)
    f2 = np.vstack([f, bad])[rng.permutation(len(f) + len(bad))]
    bvh = kernels.build_bvh(v, f2, leaf_size=4)
    assert bvh.stats.degenerate == len(bad)
    check_bvh(bvh, 4)
    o, d = scene_rays(v, f, 1500, seed=3)
    h = kernels.trace(bvh, o, d)
    hit = h.triangle >= 0
    assert np.all(f2[h.triangle[hit], 1] != f2[h.triangle[hit], 2])
    check = check_closest(v, f2, o, d, h.t, h.triangle)
    assert check.failures == 0, check.summary()


def test_all_vertices_coincident():
    """Guards the build when every triangle is degenerate (a scene box of zero size, no
    valid triangle): it must give the empty BVH, and every ray must miss."""
    v = np.full((30, 3), 0.5, np.float32)
    f = np.arange(30, dtype=np.int32).reshape(10, 3)
    bvh = kernels.build_bvh(v, f)
    assert bvh.stats.degenerate == 10
    o = np.array([[0.5, 0.5, 2.0], [0.0, 0.0, 0.0], [0.5, 0.5, 0.5]], np.float32)
    d = np.array([[0, 0, -1], [1, 1, 1], [1, 0, 0]], np.float32)
    h = kernels.trace(bvh, o, d)
    assert np.all(h.triangle == -1)


def test_duplicated_triangles_report_one_copy_at_the_right_t():
    """Guards ties between identical triangles (also with reversed winding): every ray
    that hits without duplicates hits with them at the same t; the oracle judges the rest
    (rays exactly on the grid's outer boundary may be decided either way per copy)."""
    v, f = plane_grid(4)
    dup = np.vstack([f, f, f[:, ::-1]])
    rng = np.random.default_rng(5)
    # From above and below, at vertices, edge midpoints and random points of the grid.
    o = rng.uniform(-1.5, 1.5, (800, 3)) * [1, 0.5, 1]
    o[:, 1] += np.sign(o[:, 1]) * 0.1
    target = rng.uniform(-1.2, 1.2, (800, 3))
    target[:400] = np.round(target[:400] * 8) / 8  # multiples of 0.125: vertices, edges
    target[:, 1] = 0.0
    o = o.astype(np.float32)
    d = (target - o).astype(np.float32)
    single = kernels.trace(kernels.build_bvh(v, f), o, d)
    for method in ("sah", "median"):
        h = kernels.trace(kernels.build_bvh(v, dup, method=method, leaf_size=2), o, d)
        hit = single.triangle >= 0
        assert np.all(h.triangle[hit] >= 0)
        assert np.array_equal(h.t[hit], single.t[hit])
        check = check_closest(v, dup, o, d, h.t, h.triangle)
        assert check.failures == 0, check.summary()


def test_coplanar_overlapping_triangles():
    """Guards ties between different triangles in one plane that overlap: the closest t is
    well defined (the plane's) even though the triangle is not; the hit must be one that
    covers the point, as the float64 oracle says."""
    rng = np.random.default_rng(4)
    c = rng.uniform(-1, 1, (60, 1, 2))
    xy = (c + rng.normal(scale=0.4, size=(60, 3, 2))).reshape(-1, 2)
    v = np.column_stack([xy[:, 0], np.full(len(xy), 0.25), xy[:, 1]]).astype(np.float32)
    f = np.arange(len(v), dtype=np.int32).reshape(-1, 3)
    o = np.column_stack([rng.uniform(-1.5, 1.5, 1500), rng.uniform(0.5, 2, 1500),
                         rng.uniform(-1.5, 1.5, 1500)]).astype(np.float32)
    d = np.column_stack([rng.normal(scale=0.3, size=1500), -np.ones(1500),
                         rng.normal(scale=0.3, size=1500)]).astype(np.float32)
    h = kernels.trace(kernels.build_bvh(v, f, leaf_size=2), o, d)
    check = check_closest(v, f, o, d, h.t, h.triangle)
    assert check.failures == 0, check.summary()
    assert (h.triangle >= 0).sum() > 500


def test_one_huge_and_many_tiny_triangles():
    """Guards the builder's split choice and the box test with extents 1e9 apart (a 1e4
    triangle over 3000 triangles of size 1e-5): structure exact, hits as the oracle says,
    tiny triangles found under and beside the huge one."""
    # Rays straight down at tiny triangles' centroids, and random rays onto the huge one.
    v, f, o, d = huge_over_tiny(3000)
    for method in ("sah",):  # median: see the next test
        bvh = kernels.build_bvh(v, f, method=method)
        check_bvh(bvh, 8)
        h = kernels.trace(bvh, o, d)
        check = check_closest(v, f, o, d, h.t, h.triangle)
        assert check.failures == 0, f"{method}: {check.summary()}"
        # The down rays do find the tiny triangles (all but the few seen edge-on, which
        # the oracle above has already judged).
        assert (h.triangle[:599] >= 1).sum() >= 580, (h.triangle[:599] < 1).sum()


def test_single_triangle_at_every_scale():
    """Guards the one-leaf tree (the root is a leaf): rays at its interior hit with exact
    t at every scale, rays beside it miss, from both sides."""
    for scale in (1e-15, 1e-4, 1.0, 1e4, 1e15):
        v = (np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]]) * scale).astype(np.float32)
        f = np.array([[0, 1, 2]], np.int32)
        bvh = kernels.build_bvh(v, f)
        assert bvh.stats.nodes == 1 and bvh.stats.leaves == 1
        o = (np.array([[0.25, 0.25, 1], [0.25, 0.25, -1], [0.75, 0.75, 1], [-0.1, 0.5, 1]])
             * scale).astype(np.float32)
        d = (np.array([[0, 0, -1], [0, 0, 1], [0, 0, -1], [0, 0, -1]]) * scale)
        h = kernels.trace(bvh, o, d.astype(np.float32))
        assert h.triangle.tolist() == [0, 0, -1, -1], scale
        assert np.all(h.t[:2] == 1.0), (scale, h.t)


def test_median_build_of_huge_and_tiny_triangles_does_not_corrupt_memory(device):
    """Guards the median builder against writing outside its arrays: one 2e4-wide triangle
    over 1200 triangles of size 1e-5 aborted the process ("corrupted double-linked list",
    heap corruption) inside build_bvh(method="median"); 1000 tiny triangles, or no huge
    one, build fine. Run in a child process so a crash fails this test, not the suite."""
    script = textwrap.dedent("""
        from scenesort import kernels
        from tests.kernels.reference import check_bvh
        from tests.stability.cases import huge_over_tiny
        v, f, _, _ = huge_over_tiny(1200)
        bvh = kernels.build_bvh(v, f, method="median", device=DEVICE)
        check_bvh(bvh, 8)
        print("built", bvh.stats.nodes)
    """).replace("DEVICE", repr(device))
    root = Path(__file__).resolve().parents[2]
    proc = subprocess.run([sys.executable, "-c", script], cwd=root, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, f"exit {proc.returncode}: {proc.stderr[-600:]}"
    assert "built" in proc.stdout
