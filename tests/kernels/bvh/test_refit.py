"""Refit: unchanged vertices give the built tree bit for bit; moved vertices give the hits
of a fresh build; the rebuild rule; scenes see a refit mesh."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from scenesort import kernels
from tests.kernels.reference import assert_same_hits, brute_force


def mesh(subdivisions=3):
    s = trimesh.creation.icosphere(subdivisions=subdivisions)
    return np.asarray(s.vertices, np.float32), np.asarray(s.faces, np.int32)


def wave(v: np.ndarray, amount: float) -> np.ndarray:
    """A smooth deformation: every vertex pushed along a sine of another coordinate."""
    return (v + amount * np.sin(3.0 * v[:, [1, 2, 0]])).astype(np.float32)


def rays(rng, count=3000):
    o = rng.uniform(-2.5, 2.5, (count, 3)).astype(np.float32)
    d = rng.normal(size=(count, 3)).astype(np.float32)
    return o, d


@pytest.mark.parametrize("width", [2, 4, 8])
def test_unmoved_refit_is_the_build(width):
    v, f = mesh()
    bvh = kernels.build_bvh(v, f, width=width)
    nodes, wide, blocks = (a.numpy().copy() for a in (bvh.arrays.nodes, bvh.arrays.wide,
                                                        bvh.arrays.blocks))
    out = kernels.refit_bvh(bvh, v.copy())
    assert out is bvh and out.stats.action == "refit"
    assert out.stats.sah_ratio == pytest.approx(1.0, abs=1e-9)
    assert np.array_equal(out.nodes(), nodes)
    assert np.array_equal(out.arrays.wide.numpy(), wide)
    assert np.array_equal(out.arrays.blocks.numpy(), blocks)


@pytest.mark.parametrize("width", [2, 8])
@pytest.mark.parametrize("method", ["sah", "median"])
def test_refit_hits_equal_a_fresh_build(width, method):
    """Closest hit and any hit of the refit tree equal a fresh build's of the moved mesh
    (the same triangle tests: t bit for bit), and a float64 brute force's."""
    rng = np.random.default_rng(0)
    v, f = mesh()
    bvh = kernels.build_bvh(v, f, method=method, width=width)
    moved = wave(v, 0.15)
    out = kernels.refit_bvh(bvh, moved, rebuild_ratio=np.inf)
    assert out.stats.action == "refit" and out.stats.sah_ratio > 1.0
    assert set(out.stats.phase_ms) == {"validate", "triangles", "nodes"}
    fresh = kernels.build_bvh(moved, f, method=method, width=width)
    o, d = rays(rng)
    a, b = kernels.trace(out, o, d), kernels.trace(fresh, o, d)
    assert_same_hits(a, b.t, b.triangle, rel=0.0)
    assert np.array_equal(kernels.trace(out, o, d, any_hit=True).hit, b.hit)
    ref_t, ref_tri = brute_force(moved, f, o[:500], d[:500])
    assert (a.hit[:500] != (ref_tri >= 0)).sum() <= 1
    assert np.allclose(out.bounds, [moved.min(0), moved.max(0)])
    assert np.array_equal(out.vertices, moved)


def test_a_scrambled_mesh_is_rebuilt():
    """Vertices shuffled: the refit tree's SAH cost explodes, so the mesh is rebuilt."""
    rng = np.random.default_rng(1)
    v, f = mesh()
    bvh = kernels.build_bvh(v, f)
    moved = v[rng.permutation(len(v))]
    out = kernels.refit_bvh(bvh, moved)
    assert out.stats.action == "rebuild" and out.stats.rebuild_reason == "sah"
    assert out.stats.sah_ratio > kernels.REBUILD_RATIO
    o, d = rays(rng)
    fresh = kernels.trace(kernels.build_bvh(moved, f), o, d)
    assert_same_hits(kernels.trace(out, o, d), fresh.t, fresh.triangle, rel=0.0)


def test_a_triangle_that_gains_area_forces_a_rebuild():
    """The build skips zero-area triangles; if one gets an area, refitting would lose it."""
    v, f = mesh(1)
    flat = v.copy()
    flat[f[0, 1]] = flat[f[0, 0]]  # triangle 0 (and its neighbours on that edge) collapse
    bvh = kernels.build_bvh(flat, f)
    assert bvh.stats.degenerate > 0
    out = kernels.refit_bvh(bvh, v)
    assert out.stats.action == "rebuild" and out.stats.rebuild_reason == "area"
    o = np.zeros((1, 3), np.float32)
    target = v[f[0]].astype(np.float64).mean(axis=0)
    assert kernels.trace(out, o, target[None].astype(np.float32)).triangle[0] == 0


def test_bad_vertices_name_the_field():
    v, f = mesh(1)
    bvh = kernels.build_bvh(v, f)
    with pytest.raises(ValueError, match="build's shape"):
        kernels.refit_bvh(bvh, v[:-1])
    with pytest.raises(ValueError, match="NaN"):
        kernels.refit_bvh(bvh, v * np.nan)
    with pytest.raises(ValueError, match="rebuild_ratio"):
        kernels.refit_bvh(bvh, v, rebuild_ratio=0)


def test_a_scene_sees_its_refit_mesh():
    """Refit in place: the scene rebuilt over the same Bvh traces the moved instances."""
    rng = np.random.default_rng(2)
    v, f = mesh(2)
    bvh = kernels.build_bvh(v, f)
    ts = np.stack([np.eye(3, 4, dtype=np.float32)] * 2)
    ts[1, :, 3] = (3.0, 0.0, 0.0)
    moved = wave(v, 0.2)
    kernels.refit_bvh(bvh, moved, rebuild_ratio=np.inf)
    scene = kernels.build_scene([bvh], [0, 0], ts)
    o, d = rays(rng)
    h = kernels.trace(scene, o, d)
    both = np.vstack([moved, moved + np.float32([3, 0, 0])])
    flat = kernels.trace(kernels.build_bvh(both, np.vstack([f, f + len(v)])), o, d)
    assert np.array_equal(h.hit, flat.hit)
    assert np.array_equal(h.instance[h.hit], flat.triangle[h.hit] // len(f))
