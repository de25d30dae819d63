"""Culling: on scenes larger than the view, what `visible_instances` / `visible_triangles`
leave out changes no pixel of the AO image (bit for bit), and it does leave things out."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scenesort.kernels import Camera
from scenesort.kernels.render import default_distance
from scenesort.kernels.render.cull import mesh_box, visible_instances
from scenesort.kernels.render.film import filter_reach
from scenesort.kernels.scene.api import place_instances

from scenesort import kernels


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


def visible(meshes, ids, ts, camera, dist, reach=0.0):
    """`visible_instances` from the meshes' data (no BVH), as backend/frames.py decides."""
    boxes, extents = zip(*(mesh_box(v, f) for v, f in meshes), strict=True)
    return visible_instances(place_instances(np.stack(boxes), ids, ts), np.array(extents),
                             camera, dist, reach)


@pytest.mark.parametrize("cam", sorted(CAMERAS))
def test_culled_instances_change_no_pixel(cam):
    camera = CAMERAS[cam]
    v, f = sphere()
    ts = field(14)
    ids = np.zeros(len(ts), np.int32)
    bvh = kernels.build_bvh(v, f)
    full = kernels.build_scene([bvh], ids, ts)
    dist = 0.6
    keep = visible([(v, f)], ids, ts, camera, dist)
    assert 0 < keep.sum() < 0.5 * len(ts)
    culled = kernels.build_scene([bvh], ids, ts, visible=keep)
    assert culled.stats.instances_built == keep.sum()
    o, d, tmin, tmax = camera.rays()
    normals = v[f] / np.linalg.norm(v[f], axis=2, keepdims=True)
    a = kernels.render_ao(full, o, d, spp=16, distance=dist, tmin=tmin, tmax=tmax,
                          normals=[normals])
    b = kernels.render_ao(culled, o, d, spp=16, distance=dist, tmin=tmin, tmax=tmax,
                          normals=[normals])
    assert (a.spp_used > 0).mean() > 0.3
    assert np.array_equal(a.ao, b.ao)
    # a shorter distance culls more, and still changes nothing
    near = visible([(v, f)], ids, ts, camera, 0.05)
    assert near.sum() < keep.sum() and not (near & ~keep).any()


def test_a_filters_reach_keeps_what_its_samples_see():
    """A pixel filter's samples start outside the image (Box 7 px: 3 px beyond its edges).
    A floor under the image and a strip of small squares 2.2-2.7 px right of it: culled
    for pixel centres (reach 0) the strip is left out and the filtered alpha changes;
    culled with the filter's reach it is kept, and the image is the full scene's bit for
    bit."""
    w, h = 12, 8
    m = np.eye(4)
    m[2, 3] = 5.0  # looking down -z, one world unit per pixel, raster x = world x + w / 2
    camera = Camera(matrix_world=m, width=w, height=h, type="ORTHO", ortho_scale=float(w))
    floor = np.array([[-9, -9, 0], [w / 2, -9, 0], [w / 2, 9, 0], [-9, 9, 0]], np.float32)
    quad = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    x0, size = w / 2 + 2.2, 0.25  # squares of 0.25: the lift margin is under 1 px
    squares = [np.array([[x, y, 1], [x + size, y, 1], [x + size, y + size, 1], [x, y + size, 1]],
                        np.float32) for x in (x0, x0 + size) for y in np.arange(-h, h, size)]
    strip = (np.concatenate(squares), np.concatenate([quad + 4 * i for i in range(len(squares))]))
    meshes = [(floor, quad), strip]
    ids, ts = np.array([0, 1]), np.tile(np.eye(4, dtype=np.float32)[:3], (2, 1, 1))
    bvhs = [kernels.build_bvh(v, f) for v, f in meshes]
    film = {"spp": 64, "distance": 0.05, "pixel_filter": "BOX", "filter_width": 7.0}
    reach = filter_reach("BOX", 7.0)
    assert reach == 3.0
    full = kernels.render_film(kernels.build_scene(bvhs, ids, ts), camera, **film)
    renders = {}
    for name, r in (("reach", reach), ("centres", 0.0)):
        keep = visible(meshes, ids, ts, camera, film["distance"], r)
        assert keep.tolist() == [True, name == "reach"]
        renders[name] = kernels.render_film(kernels.build_scene(bvhs, ids, ts, visible=keep),
                                            camera, **film)
    assert np.array_equal(renders["reach"].alpha, full.alpha)
    assert np.array_equal(renders["reach"].ao, full.ao)
    assert not np.array_equal(renders["centres"].alpha, full.alpha)


def test_mesh_box_is_the_bvhs_box():
    """From the mesh data alone, the box `build_bvh` gives (degenerate triangles left out:
    the scene's bounds, hence its default AO distance, do not depend on what was built)."""
    v, f = sphere()
    far = np.vstack([v, [[9.0, 9.0, 9.0]]]).astype(np.float32)  # a zero-area triangle there
    faces = np.vstack([f, [[len(v), len(v), 0]]]).astype(np.int32)
    box, extent = mesh_box(far, faces)
    assert np.array_equal(box, kernels.build_bvh(far, faces).bounds)
    assert extent == pytest.approx(float(np.ptp(v[f], axis=1).max()))
    empty, none = mesh_box(far, faces[-1:])
    assert np.isposinf(empty[0]).all() and np.isneginf(empty[1]).all() and none == 0.0


def test_unbuilt_meshes_change_no_pixel():
    """Two meshes, one only out of view: the scene without its BVH (None, its box given)
    has the full scene's bounds (so its default AO distance) and renders the same image."""
    v, f = sphere()
    cube = trimesh.creation.box(extents=(0.6, 0.6, 0.6))
    meshes = [(v, f), (np.asarray(cube.vertices, np.float32), np.asarray(cube.faces, np.int32))]
    ts = field(14)
    camera = CAMERAS["persp"]
    boxes = np.stack([mesh_box(*m)[0] for m in meshes])
    ids = (np.arange(len(ts)) % 2).astype(np.int32)
    ids[visible(meshes, np.zeros(len(ts), np.int32), ts, camera, 2.5)
        | visible(meshes, np.ones(len(ts), np.int32), ts, camera, 2.5)] = 0  # in view: spheres
    dist = default_distance(place_instances(boxes, ids, ts))  # render_ao's, of the full scene
    assert dist < 2.5
    keep = visible(meshes, ids, ts, camera, dist)
    assert keep.any() and (ids[~keep] == 1).any() and not (ids[keep] == 1).any()
    bvhs = [kernels.build_bvh(*m) for m in meshes]
    full = kernels.build_scene(bvhs, ids, ts)
    assert default_distance(full) == dist
    placed = place_instances(boxes, ids, ts)
    culled = kernels.build_scene([bvhs[0], None], ids, ts, visible=keep, placed=placed)
    assert np.array_equal(culled.bounds, full.bounds)
    assert culled.stats.meshes_built == 1 and culled.nbytes < full.nbytes
    o, d, tmin, tmax = camera.rays()
    a = kernels.render_ao(full, o, d, spp=8, tmin=tmin, tmax=tmax)  # the default distance
    b = kernels.render_ao(culled, o, d, spp=8, tmin=tmin, tmax=tmax)
    assert np.array_equal(a.ao, b.ao) and (a.spp_used > 0).mean() > 0.3
    with pytest.raises(ValueError, match="visible but its mesh 1 is None"):
        kernels.build_scene([bvhs[0], None], ids, ts, placed=placed)
    with pytest.raises(ValueError, match="pass placed"):
        kernels.build_scene([bvhs[0], None], ids, ts, visible=keep)
    with pytest.raises(ValueError, match="placed must be place_instances of these"):
        kernels.build_scene([bvhs[0], None], ids, ts[::-1], visible=keep, placed=placed)
    nothing = kernels.build_scene([None, None], ids, ts, visible=np.zeros(len(ts), bool),
                                  placed=placed)
    assert np.array_equal(nothing.bounds, full.bounds)
    assert not kernels.trace(nothing, o, d, tmin, tmax).hit.any()


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
    a = kernels.render_ao(kernels.build_bvh(verts, faces), o, d, spp=16, distance=dist,
                          tmin=tmin, tmax=tmax)
    b = kernels.render_ao(kernels.build_bvh(verts, faces[keep]), o, d, spp=16, distance=dist,
                          tmin=tmin, tmax=tmax)
    assert np.array_equal(a.ao, b.ao)


def test_distance_must_be_positive():
    v, f = sphere()
    with pytest.raises(ValueError, match="distance must be > 0"):
        kernels.visible_triangles(v, f, CAMERAS["persp"], 0.0)
