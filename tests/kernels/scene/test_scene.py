"""Two-level scenes: traversal against the flattened scene and a float64 brute force,
watertightness across mirrored and non-uniformly scaled instances, the identity instance
bit for bit, memory shared between instances, and the input checks."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scenesort.kernels.scene import bvh_nbytes

from scenesort import kernels
from tests.kernels.reference import brute_force


def rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q * np.sign(np.linalg.det(q))  # a proper rotation


def transform(rot: np.ndarray, scale, shift) -> np.ndarray:
    """float32 [M | T] with M = rot diag(scale)."""
    m = np.zeros((3, 4))
    m[:, :3] = rot * np.asarray(scale, float)
    m[:, 3] = shift
    return m.astype(np.float32)


def instance_set(rng) -> np.ndarray:
    """Identity, rotated, non-uniformly scaled, mirrored (negative determinant), far."""
    return np.stack([
        np.eye(3, 4, dtype=np.float32),
        transform(rotation(rng), (1, 1, 1), (3, 0, 0)),
        transform(rotation(rng), (0.3, 2.0, 0.7), (0, 3, 0)),
        transform(rotation(rng), (-1.0, 1.0, 1.0), (0, 0, 3)),
        transform(rotation(rng), (1.5, -0.5, 0.8), (-3, -3, 1)),
        transform(rotation(rng), (1e3, 1e3, 2e3), (2e4, -1e4, 5e3)),
    ])


def mirrors(t: np.ndarray) -> bool:
    return bool(np.linalg.det(t[:, :3].astype(np.float64)) < 0)


def flatten(instances, dtype=np.float32):
    """The world-space triangle list of ((vertices, indices), transform) instances (vertices
    M v + T in float64, rounded once to float32 as the scene's surfaces are, or exact); a
    mirroring transform's triangles reversed to keep their faces outward, as the add-on
    flattens them (addon/export.py)."""
    verts, faces, base = [], [], 0
    for (mv, mf), t in instances:
        w = mv.astype(np.float64) @ t[:, :3].astype(np.float64).T + t[:, 3]
        verts.append(w.astype(dtype))
        faces.append((mf[:, ::-1] if mirrors(t) else mf) + base)
        base += len(mv)
    return np.vstack(verts), np.vstack(faces).astype(np.int32)


def sphere(subdivisions=2):
    s = trimesh.creation.icosphere(subdivisions=subdivisions)
    return np.asarray(s.vertices, np.float32), np.asarray(s.faces, np.int32)


def torus():
    s = trimesh.creation.torus(major_radius=1.0, minor_radius=0.35, major_sections=16,
                               minor_sections=8)
    return np.asarray(s.vertices, np.float32), np.asarray(s.faces, np.int32)


def assert_gap_within_rounding(tri: np.ndarray, d: np.ndarray, dt: np.ndarray,
                               t: np.ndarray, cond: np.ndarray) -> None:
    """Hit points at t and t + dt on triangles `tri` (K, 3, 3) lie apart along the normal
    by at most what float32 rounding of the vertices and of the instance's object-space
    ray allows: |dt (n . d)| <= 16 u C (|p| + t |d|), u = 2^-24, C the transform's
    condition number (so t alone may differ much more where the ray grazes)."""
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    cos = np.abs(np.einsum("ij,ij->i", n / np.linalg.norm(n, axis=1)[:, None], d))
    reach = np.abs(tri).max(axis=(1, 2)) + t * np.abs(d).max(axis=1)
    assert np.all(np.abs(dt) * cos <= 16 * 2.0**-24 * cond * reach)


def rays_at(points: np.ndarray, rng, count: int, spread: float):
    """Rays from random points near the scene aimed at random `points` (the triangles'
    interiors: no edge case there)."""
    target = points[rng.integers(0, len(points), count)].astype(np.float64)
    o = target + spread * rng.normal(size=(count, 3)) * np.maximum(np.abs(target).max(1), 1)[
        :, None]
    return o.astype(np.float32), (target - o).astype(np.float32)


@pytest.mark.parametrize("width", [2, 8])
def test_instances_equal_the_flattened_scene(width):
    """Two meshes, six instances each (mirrored, non-uniform, far): the same instance and
    triangle as the flattened scene for rays aimed at triangle interiors, t as far apart as
    the rounding of both sides allows (`assert_gap_within_rounding`), and any-hit agreeing
    with closest hit."""
    rng = np.random.default_rng(1)
    meshes = [sphere(), torus()]
    bvhs = [kernels.build_bvh(v, f, width=width) for v, f in meshes]
    ts = instance_set(rng)
    ids = np.array([0, 1] * 3 + [1, 0] * 3, np.int32)
    transforms = np.concatenate([ts, ts[::-1]]) + np.array([0, 0, 0, 10], np.float32) * (
        np.arange(12) >= 6)[:, None, None]
    scene = kernels.build_scene(bvhs, ids, transforms)
    fv, ff = flatten([(meshes[i], t) for i, t in zip(ids, transforms, strict=True)])
    starts = np.cumsum([0] + [len(meshes[i][1]) for i in ids])
    centroids = fv[ff].astype(np.float64).mean(axis=1)
    o, d = rays_at(centroids, rng, 4000, 0.5)
    flat = kernels.trace(kernels.build_bvh(fv, ff, width=width), o, d)
    h = kernels.trace(scene, o, d)
    assert np.array_equal(h.hit, flat.hit)
    inst = np.searchsorted(starts, flat.triangle, side="right") - 1
    same = flat.hit & (h.instance == inst) & (h.triangle == flat.triangle - starts[inst])
    assert np.all(same[flat.hit])
    hit = np.flatnonzero(flat.hit)
    assert_gap_within_rounding(fv[ff[flat.triangle[hit]]].astype(np.float64), d[hit],
                               h.t[hit] - flat.t[hit].astype(np.float64), flat.t[hit],
                               scene.frames["cond"][inst[hit]])
    assert (h.instance[~h.hit] == -1).all()
    a = kernels.trace(scene, o, d, any_hit=True)
    assert np.array_equal(a.hit, h.hit)


def test_brute_force_oracle_on_a_small_instanced_scene():
    """Random rays (also missing ones) against the float64 brute force of the exact world
    geometry: hit/miss identical but for rays within float rounding of an edge."""
    rng = np.random.default_rng(2)
    v, f = sphere(1)
    ts = instance_set(rng)[:5]
    scene = kernels.build_scene([kernels.build_bvh(v, f)], np.zeros(5, np.int32), ts)
    fv, ff = flatten([((v, f), t) for t in ts], np.float64)
    o = rng.uniform(-5, 5, (3000, 3)).astype(np.float32)
    d = rng.normal(size=(3000, 3)).astype(np.float32)
    h = kernels.trace(scene, o, d)
    ref_t, ref_tri = brute_force(fv, ff, o, d)
    assert (h.hit != (ref_tri >= 0)).sum() <= 2
    both = np.flatnonzero(h.hit & (ref_tri >= 0))
    assert np.array_equal(h.instance[both], ref_tri[both] // len(f))
    assert_gap_within_rounding(fv[ff[ref_tri[both]]], d[both], h.t[both] - ref_t[both],
                               ref_t[both], scene.frames["cond"][h.instance[both]])


@pytest.mark.parametrize("width", [2, 8])
def test_no_ray_leaks_through_instanced_closed_meshes(width):
    """Rays from inside each instance of a closed icosphere to every vertex and edge
    midpoint (world images, computed in float64): every one hits that instance, mirrored,
    non-uniformly scaled and far ones included (the watertight test on the instance's
    one transformed ray, the top level's padded boxes)."""
    rng = np.random.default_rng(3)
    s = trimesh.creation.icosphere(subdivisions=3)
    v, f = np.asarray(s.vertices, np.float32), np.asarray(s.faces, np.int32)
    edges = np.asarray(s.edges_unique)
    targets = np.vstack([v, 0.5 * (v[edges[:, 0]].astype(np.float64) + v[edges[:, 1]])])
    starts = np.array([[0, 0, 0], [0.3, 0.1, -0.2], [-0.5, 0.2, 0.1]])
    ts = instance_set(rng)
    scene = kernels.build_scene([kernels.build_bvh(v, f, width=width)],
                                np.zeros(len(ts), np.int32), ts)
    for k, t in enumerate(ts):
        m, shift = t[:, :3].astype(np.float64), t[:, 3].astype(np.float64)
        o = np.repeat(starts @ m.T + shift, len(targets), axis=0).astype(np.float32)
        d = (np.tile(targets @ m.T + shift, (len(starts), 1)) - o).astype(np.float32)
        h = kernels.trace(scene, o, d)
        assert np.all(h.instance == k), f"instance {k}: {int((h.instance != k).sum())} leaked"
        assert np.all(kernels.trace(scene, o, d, any_hit=True).instance >= 0)


def test_identity_instance_is_the_mesh_bit_for_bit(shared_scene):
    """Under the identity the object-space ray is the world ray: the same hits, t, (u, v)
    and AO image, bit for bit, as the single mesh."""
    sc = shared_scene("bunny")
    bvh = kernels.build_bvh(sc.vertices, sc.indices)
    scene = kernels.build_scene([bvh], [0], np.eye(3, 4, dtype=np.float32)[None])
    cam = type(sc.camera).from_dict({**sc.camera.to_dict(), "width": 48, "height": 36})
    o, d, tmin, tmax = cam.rays()
    a, b = kernels.trace(bvh, o, d, tmin, tmax), kernels.trace(scene, o, d, tmin, tmax)
    for name in ("t", "triangle", "u", "v", "instance"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    dist = 0.05 * float(np.linalg.norm(bvh.bounds[1] - bvh.bounds[0]))
    n = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (len(sc.indices), 3, 1))
    for normals in (None, n):
        ra = kernels.render_ao(bvh, o, d, spp=8, distance=dist, tmin=tmin, tmax=tmax,
                               normals=normals)
        rb = kernels.render_ao(scene, o, d, spp=8, distance=dist, tmin=tmin, tmax=tmax,
                               normals=None if normals is None else [normals])
        assert np.array_equal(ra.ao, rb.ao)
    assert kernels.render_ao(scene, o, d, spp=4).ao.shape == (len(o),)  # default distance


@pytest.mark.parametrize("scale", [(1.0, 1.0, 1.0), (-1.0, 1.0, 1.0), (0.5, 2.0, -1.5)])
def test_ao_of_instances_equals_the_flattened_scene(scale):
    """A rotated, mirrored or non-uniformly scaled instance renders the AO of its flattened
    world-space mesh (geometric and shading normals), but for pixels whose occlusion rays
    start a rounding apart: at least 99% of pixels identical, mean difference below 1e-3."""
    rng = np.random.default_rng(4)
    v, f = torus()
    t = transform(rotation(rng), scale, (0.2, -0.1, 0.3))
    floor = np.array([[-4, -4, -1.2], [4, -4, -1.2], [4, 4, -1.2], [-4, 4, -1.2]], np.float32)
    fv, ff = flatten([((v, f), t)])
    normals = v[f] / np.linalg.norm(v[f], axis=2, keepdims=True)
    a_inv_t = np.linalg.inv(t[:, :3].astype(np.float64)).T
    world_n = (normals.astype(np.float64) @ a_inv_t.T).astype(np.float32)
    if mirrors(t):
        world_n = world_n[:, ::-1]  # the corners follow the reversed triangles
    floor_f = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    flat_v = np.vstack([fv, floor])
    flat_f = np.vstack([ff, floor_f + len(fv)])
    scene = kernels.build_scene([kernels.build_bvh(v, f), kernels.build_bvh(floor, floor_f)],
                                [0, 1], np.stack([t, np.eye(3, 4, dtype=np.float32)]))
    flat = kernels.build_bvh(flat_v, flat_f)
    cam = kernels.Camera.look_at((0, -6, 4), (0, 0, 0), (0, 0, 1), 40, 40, 30)
    o, d, tmin, tmax = cam.rays()
    for shade in (False, True):
        fn = np.vstack([world_n, np.zeros((2, 3, 3), np.float32)]) if shade else None
        sn = [normals, None] if shade else None
        ra = kernels.render_ao(flat, o, d, spp=16, distance=1.0, tmin=tmin, tmax=tmax,
                               normals=fn)
        rb = kernels.render_ao(scene, o, d, spp=16, distance=1.0, tmin=tmin, tmax=tmax,
                               normals=sn)
        assert np.mean(ra.ao == rb.ao) >= 0.99
        assert np.abs(ra.ao - rb.ao).mean() < 1e-3
        assert np.array_equal(ra.spp_used > 0, rb.spp_used > 0)


def test_instances_share_their_mesh():
    """100 instances of one mesh hold its arrays once: the scene's bytes are the BVH's
    plus the top level and the instance records."""
    v, f = sphere(3)
    bvh = kernels.build_bvh(v, f)
    rng = np.random.default_rng(5)
    ts = np.stack([transform(rotation(rng), (1, 1, 1), rng.uniform(-50, 50, 3))
                   for _ in range(100)])
    scene = kernels.build_scene([bvh], np.zeros(100, np.int32), ts)
    top = scene.nbytes - bvh_nbytes(bvh)
    assert 0 < top < 100 * 400 + 2 * 100 * 32 + 4096
    assert scene.stats.instances_built == 100


def test_bad_input_names_the_field():
    v, f = sphere(1)
    bvh = kernels.build_bvh(v, f)
    eye = np.eye(3, 4, dtype=np.float32)[None]
    with pytest.raises(ValueError, match="invertible"):
        kernels.build_scene([bvh], [0], np.zeros((1, 3, 4), np.float32))
    with pytest.raises(ValueError, match="mesh_ids must be in"):
        kernels.build_scene([bvh], [1], eye)
    with pytest.raises(ValueError, match=r"transforms must have shape \(1, 3, 4\)"):
        kernels.build_scene([bvh], [0], np.eye(4, dtype=np.float32)[None])
    with pytest.raises(ValueError, match="NaN"):
        kernels.build_scene([bvh], [0], eye * np.nan)
    with pytest.raises(ValueError, match="method must be one of"):
        kernels.build_scene([bvh], [0], eye, method="lbvh")
    with pytest.raises(ValueError, match="at least one"):
        kernels.build_scene([], [], np.zeros((0, 3, 4), np.float32))
    scene = kernels.build_scene([bvh], [0], eye)
    o = np.zeros((1, 3), np.float32)
    with pytest.raises(ValueError, match='engine="bvh"'):
        kernels.render_ao(scene, o, o + 1, engine="dacrt")
    with pytest.raises(ValueError, match="one entry per mesh"):
        kernels.render_ao(scene, o, o + 1, normals=[None, None])
    with pytest.raises(ValueError, match="per instance"):
        kernels.render_ao(scene, o, o + 1, terminator_offset=np.zeros(3))


def test_empty_scene_and_culled_instances_miss():
    v, f = sphere(1)
    scene = kernels.build_scene([kernels.build_bvh(v, f)], np.zeros(0, np.int32),
                                np.zeros((0, 3, 4), np.float32))
    o = np.zeros((2, 3), np.float32) - 3
    h = kernels.trace(scene, o, o * -1)
    assert not h.hit.any() and (h.instance == -1).all()
    hidden = kernels.build_scene([kernels.build_bvh(v, f)], [0],
                                 np.eye(3, 4, dtype=np.float32)[None], visible=np.array([False]))
    assert not kernels.trace(hidden, o, o * -1).hit.any()


def test_scene_results_do_not_depend_on_host_threads():
    """Trace and AO of a scene split between host threads equal one thread's, bit for bit."""
    rng = np.random.default_rng(6)
    v, f = torus()
    ts = instance_set(rng)[:4]
    scene = kernels.build_scene([kernels.build_bvh(v, f)], np.zeros(4, np.int32), ts)
    o, d = rays_at(flatten([((v, f), t) for t in ts])[0], rng, 20000, 0.5)
    a, b = kernels.trace(scene, o, d, threads=1), kernels.trace(scene, o, d, threads=2)
    for name in ("t", "triangle", "u", "v", "instance"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    ra = kernels.render_ao(scene, o, d, spp=4, distance=0.5, threads=1)
    rb = kernels.render_ao(scene, o, d, spp=4, distance=0.5, threads=2)
    assert np.array_equal(ra.ao, rb.ao)
