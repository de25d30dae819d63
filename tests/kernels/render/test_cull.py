"""Culling: on scenes larger than the view, what `visible_instances` / `visible_triangles`
leave out changes no pixel of the AO image (bit for bit), and it does leave things out."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

import kernels
from kernels import Camera


def sphere():
    s = trimesh.creation.icosphere(subdivisions=2, radius=0.45)
    return np.asarray(s.vertices, np.float32), np.asarray(s.faces, np.int32)


def field(n: int) -> np.ndarray:
    """(n*n, 3, 4) instances on a grid 1 apart in x and y, with a rotation each."""
    rng = np.random.default_rng(0)
    out = []
    for i in range(n):
        for j in range(n):
            q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
            t = np.zeros((3, 4))
            t[:, :3] = q * rng.uniform(0.7, 1.1, 3)
            t[:, 3] = (i - n / 2, j - n / 2, 0.0)
            out.append(t)
    return np.asarray(out, np.float32)


CAMERAS = {
    "persp": Camera.look_at((0.5, -2.5, 2.0), (0.5, 1.0, 0.0), (0, 0, 1), 35, 40, 30,
                            clip_start=0.1, clip_end=6.0),
    "ortho": Camera.from_dict({**Camera.look_at((0.0, 0.0, 4.0), (0.0, 0.3, 0.0), (0, 1, 0),
                                                35, 36, 28).to_dict(),
                               "type": "ORTHO", "ortho_scale": 3.0}),
}


@pytest.mark.parametrize("cam", sorted(CAMERAS))
def test_culled_instances_change_no_pixel(cam):
    camera = CAMERAS[cam]
    v, f = sphere()
    ts = field(14)
    bvh = kernels.build_bvh(v, f)
    full = kernels.build_scene([bvh], np.zeros(len(ts), np.int32), ts)
    dist = 0.6
    keep = kernels.visible_instances(full, camera, dist)
    assert 0 < keep.sum() < 0.5 * len(ts)
    culled = kernels.build_scene([bvh], np.zeros(len(ts), np.int32), ts, visible=keep)
    assert culled.stats["instances_built"] == keep.sum()
    o, d, tmin, tmax = camera.rays()
    normals = v[f] / np.linalg.norm(v[f], axis=2, keepdims=True)
    a = kernels.render_ao(full, o, d, 16, dist, tmin=tmin, tmax=tmax, normals=[normals])
    b = kernels.render_ao(culled, o, d, 16, dist, tmin=tmin, tmax=tmax, normals=[normals])
    assert (a.spp_used > 0).mean() > 0.3
    assert np.array_equal(a.ao, b.ao)
    # a shorter distance culls more, and still changes nothing
    near = kernels.visible_instances(full, camera, 0.05)
    assert near.sum() < keep.sum() and not (near & ~keep).any()


def test_culled_triangles_change_no_pixel():
    """One mesh of many spheres, far larger than the view: the BVH of the visible
    triangles alone renders the same image."""
    v, f = sphere()
    ts = field(12)
    verts = np.vstack([v @ t[:, :3].T + t[:, 3] for t in ts]).astype(np.float32)
    faces = np.vstack([f + k * len(v) for k in range(len(ts))]).astype(np.int32)
    camera = CAMERAS["persp"]
    dist = 0.6
    keep = kernels.visible_triangles(verts, faces, camera, dist)
    assert 0 < keep.sum() < 0.5 * len(faces)
    o, d, tmin, tmax = camera.rays()
    a = kernels.render_ao(kernels.build_bvh(verts, faces), o, d, 16, dist, tmin=tmin, tmax=tmax)
    b = kernels.render_ao(kernels.build_bvh(verts, faces[keep]), o, d, 16, dist, tmin=tmin,
                          tmax=tmax)
    assert np.array_equal(a.ao, b.ao)


def test_distance_must_be_positive():
    v, f = sphere()
    with pytest.raises(ValueError, match="distance must be > 0"):
        kernels.visible_triangles(v, f, CAMERAS["persp"], 0.0)
