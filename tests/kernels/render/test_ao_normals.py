"""Shading normals (`normals=`) and Cycles' shadow terminator offset in AO: flat corners
are the geometric definition, back faces turn their normals, smooth low-poly spheres show
the terminator and its offset, DACRT agrees, and bad input names the argument."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scenesort.kernels import Camera

from scenesort import kernels


def floor_and_sphere(subdivisions: int = 1):
    """A 4 x 4 floor (z = 0, two triangles) under a unit icosphere resting on it, and the
    sphere's smooth corner normals (its vertex directions; the floor's corners are zero:
    flat)."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    sv = np.asarray(sphere.vertices, np.float64)
    sf = np.asarray(sphere.faces, np.int32)
    floor_v = np.array([[-2, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0]], np.float64)
    floor_f = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    vertices = np.concatenate([floor_v, sv + [0.0, 0.0, 1.0]]).astype(np.float32)
    indices = np.concatenate([floor_f, sf + 4]).astype(np.int32)
    unit = sv / np.linalg.norm(sv, axis=1, keepdims=True)
    normals = np.concatenate([np.zeros((2, 3, 3)), unit[sf]]).astype(np.float32)
    return vertices, indices, normals


def face_normals(vertices: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """Each triangle's geometric normal (its winding's) on all three corners, (T, 3, 3)."""
    v = vertices.astype(np.float64)[indices]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return np.repeat(n[:, None, :], 3, axis=1).astype(np.float32)


def rays(position, look_at, width: int = 48, height: int = 36, up=(0, 0, 1)):
    return Camera.look_at(position, look_at, up, 40.0, width, height).rays()


@pytest.fixture(scope="module")
def floor_sphere():
    vertices, indices, normals = floor_and_sphere()
    bvh = kernels.build_bvh(vertices, indices)
    o, d, tmin, tmax = rays((0.0, -5.0, 2.0), (0.0, 0.0, 0.8))
    return bvh, normals, (o, d), {"tmin": tmin, "tmax": tmax}


def test_zero_corners_are_the_geometric_definition_bit_for_bit(floor_sphere):
    """Three zero corners mean "flat": the geometric normal and no lift, so every sample
    is the one `normals=None` takes (None is today's definition, unchanged)."""
    bvh, normals, (o, d), clip = floor_sphere
    kw = {"spp": 16, "seed": 3, "distance": 2.0, **clip}
    flat = kernels.render_ao(bvh, o, d, **kw)
    zeros = kernels.render_ao(bvh, o, d, normals=np.zeros_like(normals), **kw)
    assert 0.0 < flat.ao[flat.spp_used > 0].min() < 1.0
    np.testing.assert_array_equal(flat.ao, zeros.ao)
    np.testing.assert_array_equal(flat.spp_used, zeros.spp_used)


def test_face_normals_give_the_geometric_answer(floor_sphere):
    """A flat mesh whose corner normals are its face normals renders as with None (the
    directions may differ in a last bit: a sample in a thousand may flip)."""
    bvh, _, (o, d), clip = floor_sphere
    kw = {"spp": 32, "seed": 5, "distance": 2.0, **clip}
    normals = face_normals(bvh.vertices, bvh.indices)
    flat = kernels.render_ao(bvh, o, d, **kw)
    faces = kernels.render_ao(bvh, o, d, normals=normals, **kw)
    np.testing.assert_array_equal(flat.spp_used, faces.spp_used)
    hit = flat.spp_used > 0
    assert np.mean(flat.ao[hit] == faces.ao[hit]) > 0.98
    assert np.abs(flat.ao - faces.ao).max() <= 2.0 / 32 + 1e-6


def test_a_normal_turned_away_from_the_ray_is_flipped():
    """A floor seen from below, its normals pointing up (away from the viewer): they turn
    with the geometric normal toward the viewer, where a box hangs below the floor. Kept
    as given, the hemisphere would look up into nothing (AO 1 everywhere)."""
    v = [[-2, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0]]
    box = trimesh.creation.box(extents=(0.8, 0.8, 0.4))
    box.apply_translation((0.6, 0.0, -0.4))
    vertices = np.concatenate([np.float64(v), box.vertices]).astype(np.float32)
    indices = np.concatenate([[[0, 1, 2], [0, 2, 3]], np.asarray(box.faces) + 4]).astype(np.int32)
    up = face_normals(vertices, indices)
    assert np.all(up[:2, :, 2] == 1.0)  # the floor's normals point up, away from the camera
    bvh = kernels.build_bvh(vertices, indices)
    o, d, tmin, tmax = rays((-0.5, -0.3, -3.0), (-0.5, -0.3, 0.0), 32, 32, up=(0, 1, 0))
    kw = {"spp": 64, "seed": 1, "distance": 1.0, "tmin": tmin, "tmax": tmax}
    geometric = kernels.render_ao(bvh, o, d, **kw)
    given = kernels.render_ao(bvh, o, d, normals=up, **kw)
    hit = geometric.spp_used > 0
    assert hit.mean() > 0.5 and geometric.ao[hit].min() < 0.8  # the box darkens the floor
    assert np.mean(geometric.ao[hit] == given.ao[hit]) > 0.98
    assert abs(geometric.ao[hit].mean() - given.ao[hit].mean()) < 1e-3


def test_smooth_low_poly_sphere_shows_the_terminator_and_its_offset_lifts_it():
    """A convex mesh never occludes itself with geometric normals (AO exactly 1). With
    smooth normals, the directions of the shading hemisphere below a facet run into the
    sphere (Cycles traces them), so AO drops near the facets' edges; Cycles' terminator
    offset lifts those rays toward the smooth surface, over the neighbouring facets, so
    AO rises again (here back to 1). A per-triangle offset array of the same value is the
    same render."""
    sphere = trimesh.creation.icosphere(subdivisions=1, radius=1.0)
    vertices = np.asarray(sphere.vertices, np.float32)
    indices = np.asarray(sphere.faces, np.int32)
    unit = sphere.vertices / np.linalg.norm(sphere.vertices, axis=1, keepdims=True)
    normals = unit[indices].astype(np.float32)
    bvh = kernels.build_bvh(vertices, indices)
    o, d, tmin, tmax = rays((0.0, -4.0, 0.5), (0.0, 0.0, 0.0), 40, 40)
    kw = {"spp": 256, "seed": 2, "distance": 3.0, "tmin": tmin, "tmax": tmax}
    flat = kernels.render_ao(bvh, o, d, **kw)
    hit = flat.spp_used > 0
    assert hit.mean() > 0.2 and np.all(flat.ao[hit] == 1.0)
    none = kernels.render_ao(bvh, o, d, normals=normals, terminator_offset=0.0, **kw).ao[hit]
    lifted = kernels.render_ao(bvh, o, d, normals=normals, **kw).ao[hit]  # 0.1, Blender's
    spread = np.sqrt(np.sum(none * (1 - none)) / kw["spp"]) / hit.sum()  # independent SE
    assert none.mean() < 1.0 - 10 * spread  # the terminator: rays below facets hit the sphere
    assert lifted.mean() - none.mean() > 10 * spread
    assert lifted.mean() > 0.999  # measured: 0.992 without the lift, 1.0 with it
    per_triangle = np.full(len(indices), 0.1, np.float32)
    again = kernels.render_ao(bvh, o, d, normals=normals, terminator_offset=per_triangle, **kw)
    np.testing.assert_array_equal(again.ao[hit], lifted)


def test_dacrt_traces_the_same_smooth_rays(floor_sphere):
    bvh, normals, (o, d), clip = floor_sphere
    kw = {"spp": 8, "seed": 4, "distance": 2.0, "normals": normals, **clip}
    with_bvh = kernels.render_ao(bvh, o, d, **kw)
    with_dacrt = kernels.render_ao(bvh, o, d, engine="dacrt", **kw)
    assert with_bvh.rays.occlusion > 0
    np.testing.assert_array_equal(with_bvh.ao, with_dacrt.ao)


@pytest.mark.parametrize(
    "kwargs,match",
    [({"normals": np.zeros((5, 3, 3), np.float32)}, r"normals must have shape \(6, 3, 3\)"),
     ({"normals": np.full((6, 3, 3), np.nan, np.float32)}, "normals contains NaN"),
     ({"normals": np.zeros((6, 3, 3), np.int32)}, "normals must be a float32"),
     ({"normals": np.zeros((6, 3, 3), np.float32), "terminator_offset": 1.5},
      r"terminator_offset must lie in \[0, 1\]"),
     ({"normals": np.zeros((6, 3, 3), np.float32), "terminator_offset": np.zeros(2)},
      r"terminator_offset must be a number or have shape \(6,\)")],
)
def test_bad_normals_name_the_argument(kwargs, match):
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float32)
    f = np.array([[0, 1, 2], [1, 3, 2]] * 3, np.int32)
    bvh = kernels.build_bvh(v, f)
    with pytest.raises(ValueError, match=match):
        kernels.ambient_occlusion(bvh, np.float32([[0.2, 0.2, 1]]), np.float32([[0, 0, -1]]),
                                  **kwargs)
