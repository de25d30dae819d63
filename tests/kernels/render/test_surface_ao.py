"""AO at given surface points (a bake's texels): the same numbers as a camera render whose
primary rays hit those points from the front, the error target on points, points on
triangles without area, and clear errors for points that are not on the mesh."""

from __future__ import annotations

import numpy as np
import pytest

from scenesort import kernels


@pytest.fixture(scope="module")
def bunny(shared_scene):
    scene = shared_scene("bunny")
    return scene, kernels.build_bvh(scene.vertices, scene.indices)


def _front_hits(scene, bvh):
    """The scene camera's rays that hit a front face (their hits' triangle, u, v) and
    those rays."""
    origins, directions, _, _ = scene.camera.rays()
    hits = kernels.trace(bvh, origins, directions)
    corners = scene.vertices[scene.indices[np.maximum(hits.triangle, 0)]]
    ng = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    front = hits.hit & (np.einsum("ij,ij->i", ng, directions) < 0.0)
    keep = np.flatnonzero(front)
    return hits, keep, origins[keep], directions[keep]


@pytest.mark.parametrize("settings", [dict(spp=16, seed=5), dict(target_error=0.03, seed=2)])
def test_points_give_the_camera_renders_numbers(bunny, settings) -> None:
    """A point's occlusion rays, samples and random numbers are those of the primary ray
    that hit it there (same index): bit for bit, fixed samples and to an error target."""
    scene, bvh = bunny
    hits, keep, origins, directions = _front_hits(scene, bvh)
    assert len(keep) > 500
    render = kernels.render_ao(bvh, origins, directions, distance=0.05, **settings)
    baked = kernels.surface_ao(bvh, hits.triangle[keep], hits.u[keep], hits.v[keep],
                               distance=0.05, **settings)  # fmt: skip
    np.testing.assert_array_equal(baked.ao, render.ao)
    np.testing.assert_array_equal(baked.spp_used, render.spp_used)
    np.testing.assert_array_equal(baked.normals, render.normals)
    assert baked.rmse_estimate == render.rmse_estimate and baked.rays.primary == 0
    assert 0.05 < baked.ao.mean() < 0.95


def test_shading_normals_and_offsets_apply_as_in_a_render(bunny) -> None:
    scene, bvh = bunny
    hits, keep, origins, directions = _front_hits(scene, bvh)
    normals = np.repeat(np.array([[[0.0, 0.0, 1.0]]], np.float32), 3, axis=1)
    normals = np.broadcast_to(normals, (len(scene.indices), 3, 3)).copy()
    shade = dict(spp=8, distance=0.05, normals=normals, terminator_offset=0.3)
    render = kernels.render_ao(bvh, origins, directions, **shade)
    baked = kernels.surface_ao(bvh, hits.triangle[keep], hits.u[keep], hits.v[keep], **shade)
    np.testing.assert_array_equal(baked.ao, render.ao)
    flat = kernels.surface_ao(bvh, hits.triangle[keep], hits.u[keep], hits.v[keep], spp=8,
                              distance=0.05)  # fmt: skip
    assert not np.array_equal(flat.ao, baked.ao)  # the normals changed something


def test_an_open_plane_is_unoccluded_and_a_floor_under_a_roof_is_dark() -> None:
    """Independent cases: a lone triangle's front sees nothing (AO 1 exactly); a floor
    point under a roof 0.001 above, reaching 100 units every way, with AO distance 1, is
    occluded in every one of its 256 directions (only a cosine-weighted direction within
    0.001 of the horizon, 1 in a million, would pass)."""
    floor = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    roof = np.array([[-50, -50, 1e-3], [-50, 150, 1e-3], [150, -50, 1e-3]], np.float32)
    pts = dict(u=np.full(8, 0.25, np.float32), v=np.full(8, 0.25, np.float32))
    lone = kernels.build_bvh(floor, np.array([[0, 1, 2]], np.int32))
    open_ao = kernels.surface_ao(lone, np.zeros(8, np.int32), spp=32, distance=1.0, **pts)
    assert np.all(open_ao.ao == 1.0) and np.all(open_ao.spp_used == 32)
    covered = kernels.build_bvh(np.concatenate([floor, roof]),
                                np.array([[0, 1, 2], [3, 4, 5]], np.int32))  # fmt: skip
    dark = kernels.surface_ao(covered, np.zeros(8, np.int32), spp=32, distance=1.0, **pts)
    assert np.all(dark.spp_used == 32)
    assert np.all(dark.ao == 0.0)


def test_points_on_triangles_without_area_are_left_out() -> None:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0]], np.float32)
    f = np.array([[0, 1, 2], [0, 1, 3]], np.int32)  # the second has no area
    bvh = kernels.build_bvh(v, f)
    out = kernels.surface_ao(bvh, np.array([0, 1, 0], np.int32), np.full(3, 0.2, np.float32),
                             np.full(3, 0.2, np.float32), spp=4)  # fmt: skip
    assert out.spp_used.tolist() == [4, 0, 4] and out.ao[1] == 1.0


@pytest.mark.parametrize(("triangles", "u", "v", "match"), [
    ([0, 2], [0.1, 0.1], [0.1, 0.1], r"triangles must lie in \[0, 1\]"),
    ([0, -1], [0.1, 0.1], [0.1, 0.1], r"triangles must lie in"),
    ([0.5], [0.1], [0.1], "triangles must be a 1-D integer array"),
    ([0, 1], [0.1], [0.1, 0.1], r"u must be a scalar or have shape \(2,\)"),
    ([0, 1], [0.6, 0.1], [0.6, 0.1], "point 0 has u=0.6"),
    ([0, 1], [0.1, np.nan], [0.1, 0.1], "u contains NaN"),
    ([0, 1], [0.1, -0.1], [0.1, 0.1], "point 1 has u=-0.1"),
])  # fmt: skip
def test_points_off_the_mesh_are_refused_by_name(triangles, u, v, match) -> None:
    v3 = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float32)
    bvh = kernels.build_bvh(v3, np.array([[0, 1, 2], [1, 3, 2]], np.int32))
    with pytest.raises(ValueError, match=match):
        kernels.surface_ao(bvh, np.asarray(triangles), np.asarray(u, np.float32),
                           np.asarray(v, np.float32))  # fmt: skip


def test_dacrt_and_denoise_are_refused() -> None:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    bvh = kernels.build_bvh(v, np.array([[0, 1, 2]], np.int32))
    for bad in (dict(engine="dacrt"), dict(denoise=True)):
        with pytest.raises(ValueError, match="surface_ao traces with engine='bvh'"):
            kernels.surface_ao(bvh, [0], [0.2], [0.2], **bad)
