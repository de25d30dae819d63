"""BVH construction on the task pool: exact structure, statistics and errors."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scenesort import kernels

from ..engine_digests import depth_first
from ..reference import check_bvh, random_soup


@pytest.mark.parametrize("method", ["sah", "median"])
@pytest.mark.parametrize("leaf_size", [1, 8, 16, 32])
def test_structure_on_random_soups(method, leaf_size):
    rng = np.random.default_rng(leaf_size)
    for triangles in (1, 2, 9, 33, 500, 5000):
        v, f = random_soup(rng, triangles)
        bvh = kernels.build_bvh(v, f, method=method, leaf_size=leaf_size)
        check_bvh(bvh, leaf_size)


@pytest.mark.parametrize("method", ["sah", "median"])
def test_structure_on_shared_scene(method, shared_scene):
    scene = shared_scene("bunny")
    bvh = kernels.build_bvh(scene.vertices, scene.indices, method=method)
    check_bvh(bvh, 8)
    stats = bvh.stats
    assert stats.triangles == len(scene.indices)
    assert set(stats.phase_ms) >= {"SplitPlane", "PPS", "Swap", "AABB"}
    assert stats.build_ms > 0 and stats.sah_cost > 1.0
    # The spatial median needs the AABB phase; binned SAH takes the boxes from its bins.
    assert (stats.phase_ms["AABB"] > 0) == (method == "median")
    assert (stats.phase_ms["SplitPlane"] > 0) == (method == "sah")


def test_sah_cost_statistic_matches_a_float64_sum(shared_scene):
    scene = shared_scene("bunny")
    bvh = kernels.build_bvh(scene.vertices, scene.indices)
    nodes = bvh.nodes()
    e = np.maximum(nodes["hi"].astype(np.float64) - nodes["lo"], 0.0)
    area = e[:, 0] * e[:, 1] + e[:, 1] * e[:, 2] + e[:, 2] * e[:, 0]
    expected = np.sum(area * np.where(nodes["count"] > 0, nodes["count"], 1)) / area[0]
    assert bvh.stats.sah_cost == pytest.approx(expected, rel=1e-6)


def test_cpu_build_reads_the_callers_arrays_in_place():
    """On CPU float32 vertices and int32 indices are the BVH's mesh themselves (docs/
    kernels-api.md: read as Embree reads shared buffers), not copies; other dtypes are
    converted once."""
    v, f = random_soup(np.random.default_rng(11), 300)
    v, f = v.astype(np.float32), f.astype(np.int32)
    bvh = kernels.build_bvh(v, f, device="cpu")
    assert bvh.mesh.v.ptr == v.ctypes.data and bvh.mesh.f.ptr == f.ctypes.data
    assert bvh.arrays.vertices.ptr == v.ctypes.data
    converted = kernels.build_bvh(v.astype(np.float64), f.astype(np.int64), device="cpu")
    assert converted.mesh.v.ptr != v.ctypes.data
    assert np.array_equal(converted.mesh.v.numpy(), v)
    assert np.array_equal(converted.mesh.f.numpy(), f)


@pytest.mark.parametrize("width", [2, 4, 8])
def test_bvh_bytes_statistic_counts_right_sized_arrays(width, shared_scene):
    """bvh_bytes from the tree's own counts and the documented layouts (32-byte nodes, an
    id per leaf-order triangle and, for the binary traversal alone, its 36 bytes of
    vertices, 32 bytes per lane of a wide node, 160-byte leaf blocks): the arrays the Bvh
    keeps are no larger than the tree (no worst-case buffer kept alive behind a view)."""
    scene = shared_scene("conference")  # degenerate triangles: fewer in the tree than given
    s = kernels.build_bvh(scene.vertices, scene.indices, width=width).stats
    n = s.triangles - s.degenerate
    # width 2: a one-word placeholder each for the wide nodes and blocks
    # width 2: one-entry placeholders for the wide nodes and blocks; else for tri_verts
    wide = 8 if width == 2 else 32 * width * s.wide_nodes + 160 * s.leaf_blocks
    leaf_vertices = 36 * n if width == 2 else 12
    assert s.bvh_bytes == 32 * s.nodes + 4 * n + leaf_vertices + wide


def test_in_place_exchange_gives_the_pools_tree(shared_scene):
    """One worker with every step inline partitions every SAH task in place in one pass
    (build.exchange_in_place); 64 workers with K = 1 send all but the smallest through
    PPS and Swap's two steps. The exchange is the same, so the trees are the same: node
    for node and in leaf order. The bunny has coincident centroids (halving) too."""
    scene = shared_scene("bunny")
    rng = np.random.default_rng(5)
    for v, f in ((scene.vertices, scene.indices), random_soup(rng, 20_000)):
        serial = kernels.build_bvh(v, f, workers=1, min_chunks=10**6)
        pooled = kernels.build_bvh(v, f, workers=64, min_chunks=1)
        assert serial.stats.pool_steps_published == 0
        assert pooled.stats.pool_steps_published > 100
        (a_nodes, a_perm), (b_nodes, b_perm) = depth_first(serial), depth_first(pooled)
        assert np.array_equal(a_perm, b_perm)
        assert a_nodes.tobytes() == b_nodes.tobytes()


def test_sah_beats_median_on_a_real_scene(shared_scene):
    scene = shared_scene("sponza")
    sah = kernels.build_bvh(scene.vertices, scene.indices, method="sah")
    median = kernels.build_bvh(scene.vertices, scene.indices, method="median")
    assert sah.stats.sah_cost < median.stats.sah_cost


def test_degenerate_triangles_are_skipped_and_counted():
    rng = np.random.default_rng(3)
    v, f = random_soup(rng, 200)
    f[:10, 1] = f[:10, 0]  # repeated vertex
    v = np.vstack([v, [[0, 0, 0], [1, 1, 1], [2, 2, 2]]]).astype(np.float32)
    n = len(v)
    f[10] = [n - 3, n - 2, n - 1]  # collinear
    bvh = kernels.build_bvh(v, f)
    assert bvh.stats.degenerate == 11
    check_bvh(bvh, 8)


def test_coincident_centroids_fall_back_to_halving():
    """Many copies of one triangle: no plane separates them, the build still terminates."""
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    f = np.zeros((100, 3), np.int32) + [0, 1, 2]
    for method in ("sah", "median"):
        bvh = kernels.build_bvh(v, f, method=method, leaf_size=4)
        check_bvh(bvh, 4)


def test_depth_cap_makes_big_leaves():
    rng = np.random.default_rng(4)
    v, f = random_soup(rng, 300)
    bvh = kernels.build_bvh(v, f, leaf_size=1, max_depth=3)
    assert bvh.stats.depth <= 2
    check_bvh(bvh, 1, max_depth=3)


def test_sah_splits_below_the_leaf_size_where_that_is_cheaper():
    """leaf_size is a maximum for SAH: two far-apart small triangles get a leaf each, while
    copies of one triangle (nothing to gain from splitting) share one leaf. A CPU build for
    a wide tree leaves ranges of at most wide.WHOLE triangles uncut: the collapse makes one
    leaf block of them either way."""
    tri = np.array([[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0]], np.float32)
    v = np.vstack([tri, tri + 100]).astype(np.float32)
    bvh = kernels.build_bvh(v, np.array([[0, 1, 2], [3, 4, 5]], np.int32), leaf_size=8,
                            width=2)
    check_bvh(bvh, 8)
    assert bvh.stats.leaves == 2
    wide = kernels.build_bvh(v, np.array([[0, 1, 2], [3, 4, 5]], np.int32), leaf_size=8,
                             width=8, device="cpu")
    check_bvh(wide, 8)
    assert wide.stats.leaves == 1 and wide.stats.leaf_blocks == 1
    copies = kernels.build_bvh(tri, np.zeros((8, 3), np.int32) + [0, 1, 2], leaf_size=8)
    assert copies.stats.leaves == 1
    median = kernels.build_bvh(v, np.array([[0, 1, 2], [3, 4, 5]], np.int32), method="median")
    assert median.stats.leaves == 1  # the spatial median splits only above leaf_size


@pytest.mark.parametrize("max_depth", [1, 2, 3, 5])
def test_depth_cap_inside_small_subtrees(max_depth):
    """Ranges small enough to be built in one worker keep the depth cap too."""
    rng = np.random.default_rng(max_depth)
    v, f = random_soup(rng, 40)
    bvh = kernels.build_bvh(v, f, leaf_size=1, max_depth=max_depth)
    assert bvh.stats.depth <= max_depth - 1
    check_bvh(bvh, 1, max_depth=max_depth)


def test_empty_mesh_builds():
    bvh = kernels.build_bvh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))
    assert bvh.stats.nodes == 1 and bvh.stats.triangles == 0


@pytest.mark.parametrize(
    ("vertices", "indices", "message"),
    [
        (np.array([[0, 0, np.nan]] * 3, np.float32), [[0, 1, 2]], "NaN or Inf"),
        (np.array([[0, 0, np.inf]] * 3, np.float32), [[0, 1, 2]], "NaN or Inf"),
        (np.zeros((3, 3), np.float32), [[0, 1, 3]], "indices must lie in"),
        (np.zeros((3, 3), np.float32), [[0, -1, 2]], "indices must lie in"),
        (np.zeros((3, 2), np.float32), [[0, 1, 2]], "vertices must have shape"),
        (np.zeros((3, 3), np.int32), [[0, 1, 2]], "vertices must be a float32"),
        (np.zeros((3, 3), np.float32), [[0.0, 1.0, 2.0]], "indices must be an int32"),
        (np.zeros((3, 3), np.float32), [0, 1, 2], "indices must have shape"),
    ],
)
def test_bad_input_is_rejected(vertices, indices, message):
    with pytest.raises(ValueError, match=message):
        kernels.build_bvh(vertices, np.asarray(indices))


def test_bad_options_are_rejected():
    v, f = random_soup(np.random.default_rng(0), 4)
    with pytest.raises(ValueError, match="method must be one of"):
        kernels.build_bvh(v, f, method="lbvh")
    with pytest.raises(ValueError, match="leaf_size"):
        kernels.build_bvh(v, f, leaf_size=0)


@settings(max_examples=25, deadline=None)
@given(
    triangles=st.integers(1, 300),
    leaf_size=st.sampled_from([1, 2, 8, 32]),
    method=st.sampled_from(["sah", "median"]),
    seed=st.integers(0, 2**32 - 1),
    grid=st.sampled_from([None, 4]),
)
def test_structure_property(triangles, leaf_size, method, seed, grid):
    """Random soups, also snapped to a coarse grid (many shared and coincident vertices)."""
    rng = np.random.default_rng(seed)
    v, f = random_soup(rng, triangles)
    if grid:
        v = np.floor(v * grid).astype(np.float32)
    bvh = kernels.build_bvh(v, f, method=method, leaf_size=leaf_size)
    check_bvh(bvh, leaf_size)


@pytest.mark.slow
@pytest.mark.host_only  # a child process compiling for the CPU
def test_compile_time_is_reported_apart_from_build_time(tmp_path):
    """The first build in an empty kernel cache compiles Warp modules for seconds: that is
    `compile_ms`, not `build_ms` (a first `scenesort render` printed "build 7095 ms" for a
    71 ms build). Run in a child process with a cache of its own."""
    code = textwrap.dedent("""
        import json
        from scenesort import kernels
        from scenesort.backend.render.scenes import default_scene
        scene = default_scene(64, 48)
        first = kernels.build_bvh(scene.vertices, scene.indices, device="cpu").stats
        again = kernels.build_bvh(scene.vertices, scene.indices, device="cpu").stats
        print(json.dumps([first.compile_ms, first.build_ms, again.compile_ms,
                          again.build_ms]))
    """)
    env = {**os.environ, "WARP_CACHE_PATH": str(tmp_path)}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True, cwd=Path(__file__).resolve().parents[3]).stdout
    compile_first, build_first, compile_again, build_again = json.loads(out.splitlines()[-1])
    assert compile_first > 500.0  # an empty cache: the build module compiled
    assert compile_again < 50.0  # loaded, nothing to compile
    assert build_first < 0.5 * compile_first and build_again < 0.5 * compile_first
