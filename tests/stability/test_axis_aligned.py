"""Axis-aligned rays (exactly zero direction components, -0.0 included), rays that start
on a box face or travel inside a zero-thickness box, and rays parallel to a triangle's
plane: the inputs where a slab test computes 0 * inf and a triangle test divides by 0."""

from __future__ import annotations

import numpy as np
import pytest

from scenesort import kernels

from .cases import Check, box_room, check_closest, check_reported, plane_grid, transform


def room(scale: float = 1.0, offset: float = 0.0):
    v, f = box_room(4)
    return transform(v, scale, offset).astype(np.float32), f


def in_wall_rays(v: np.ndarray, negative_zero: bool):
    """Rays that start on each of the room's six walls (the faces of the root box and of
    flat leaf boxes) and travel inside that wall's plane, along the other two axes and
    along their diagonals, so every direction has at least one exactly zero component."""
    lo, hi = v.min(axis=0), v.max(axis=0)
    g = np.array([0.3, 0.55, 0.8])  # interior fractions, never on a grid line
    origins, directions = [], []
    for axis in range(3):
        a, b = (axis + 1) % 3, (axis + 2) % 3
        for wall in (lo[axis], hi[axis]):
            for fa in g:
                for fb in g:
                    p = np.zeros(3, np.float32)
                    p[axis] = wall
                    p[a] = lo[a] + fa * (hi[a] - lo[a])
                    p[b] = lo[b] + fb * (hi[b] - lo[b])
                    for da, db in ((1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (-1, 1)):
                        d = np.full(3, -0.0 if negative_zero else 0.0, np.float32)
                        d[a], d[b] = da, db
                        origins.append(p)
                        directions.append(d)
    return np.array(origins, np.float32), np.array(directions, np.float32)


@pytest.mark.parametrize(("scale", "offset"), [(1.0, 0.0), (1e-3, 1.0), (1e3, 1e5)])
@pytest.mark.parametrize("negative_zero", [False, True], ids=["+0", "-0"])
def test_rays_inside_a_wall_plane_hit_the_perpendicular_wall(scale, offset, negative_zero):
    """Guards the slab test for origins exactly on a box face with the ray parallel to it
    (the face must count as inside, with no 0 * inf = NaN), the triangle test for rays in a
    triangle's plane (a miss, never a division by zero), and watertightness on the room's
    corner edges, where such a ray meets the next wall exactly on its edge."""
    v, f = room(scale, offset)
    o, d = in_wall_rays(v, negative_zero)
    for method in ("sah", "median"):
        h = kernels.trace(kernels.build_bvh(v, f, method=method, leaf_size=2), o, d)
        check = Check(rays=len(o))
        fail = check_reported(v, f, o, d, h.t, h.triangle, check) | (h.triangle < 0)
        check.add("escaped", h.triangle < 0)
        assert not fail.any(), f"{method}: {int(fail.sum())} of {len(o)} failed {check.kinds}"
        # The hit is on the wall the ray runs into, never on the wall it travels in.
        n = np.cross(v[f[h.triangle, 1]] - v[f[h.triangle, 0]],
                     v[f[h.triangle, 2]] - v[f[h.triangle, 0]])
        assert np.all(np.abs(np.sum(n * d, axis=1)) > 0)


def test_axis_rays_from_a_box_face_inward_and_outward():
    """Guards rays whose origin lies exactly on the root box's face: pointing inward they
    must reach the opposite wall (t exactly the room's width; tmin skips the wall they
    start on), pointing outward they must find nothing."""
    v, f = room()
    lo, hi = v.min(axis=0), v.max(axis=0)
    bvh = kernels.build_bvh(v, f)
    g = np.linspace(0.1, 0.9, 5)
    for axis in range(3):
        a, b = (axis + 1) % 3, (axis + 2) % 3
        ga, gb = np.meshgrid(lo[a] + g * (hi[a] - lo[a]), lo[b] + g * (hi[b] - lo[b]))
        o = np.zeros((ga.size, 3), np.float32)
        o[:, a], o[:, b], o[:, axis] = ga.ravel(), gb.ravel(), lo[axis]
        inward = np.zeros_like(o)
        inward[:, axis] = 1.0
        h = kernels.trace(bvh, o, inward, tmin=1e-3)
        assert np.all(h.triangle >= 0)
        assert np.all(h.t == hi[axis] - lo[axis])
        out = kernels.trace(bvh, o, -inward, tmin=1e-3)
        assert np.all(out.triangle < 0) and np.all(np.isinf(out.t))


@pytest.mark.parametrize("negative_zero", [False, True], ids=["+0", "-0"])
def test_axis_rays_through_every_grid_vertex_and_edge(negative_zero):
    """Guards watertightness for axis-aligned rays on an axis-aligned grid: a ray along -y
    through an interior grid vertex or edge midpoint has two exactly zero direction
    components and zero edge functions, and must still hit, at exactly t = 1."""
    v, f = plane_grid(8)  # y = 0, x and z in [-1, 1], vertices at multiples of 0.25
    xs = np.linspace(-0.875, 0.875, 15)  # interior vertices and edge midpoints
    gx, gz = np.meshgrid(xs, xs)
    o = np.stack([gx.ravel(), np.ones(gx.size), gz.ravel()], axis=1).astype(np.float32)
    z = -0.0 if negative_zero else 0.0
    d = np.tile(np.array([[z, -1.0, z]], np.float32), (len(o), 1))
    h = kernels.trace(kernels.build_bvh(v, f), o, d)
    assert np.all(h.triangle >= 0), f"{int((h.triangle < 0).sum())} of {len(o)} escaped"
    assert np.all(h.t == 1.0)
    # Along the diagonals of the quads too (the shared hypotenuse edges), with one zero.
    d2 = np.tile(np.array([[0.25, -1.0, z]], np.float32), (len(o), 1))
    h2 = kernels.trace(kernels.build_bvh(v, f), o, d2)
    inside = np.abs(o[:, 0] + 0.25) < 1.0
    assert np.all(h2.triangle[inside] >= 0)
    assert np.all(h2.t[inside] == 1.0)


def test_rays_parallel_to_a_tilted_triangle_never_hit_it():
    """Guards the parallel case off the axes: rays lying exactly in the plane
    x + y + z = 1 (exactly representable) or parallel to it one ulp away have a zero
    determinant: they must miss, without NaN, whether or not they cross the triangle."""
    v = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
    f = np.array([[0, 1, 2]], np.int32)
    bvh = kernels.build_bvh(v, f)
    o = np.array([[2, -1, 0], [-1, 2, 0], [0.5, 0.5, 0], [0.25, 0.25, 0.5], [0, 0, 1]],
                 np.float32)
    d = np.array([[-1, 1, 0], [1, -1, 0], [0, -1, 1], [1, -1, 0], [1, 0, -1]], np.float32)
    assert np.all(o.sum(axis=1) == 1) and np.all(d.sum(axis=1) == 0)
    for shift in (0.0, 1.2e-7, -1.2e-7):
        h = kernels.trace(bvh, o + np.float32(shift), d)
        assert np.all(h.triangle == -1) and np.all(np.isinf(h.t))


def test_nearly_parallel_rays_agree_with_float64():
    """Guards grazing rays that do cross a triangle's plane at tiny angles (1e-7 .. 1e-2
    rad): hit or miss as the float64 oracle decides away from edges, t within 2 ulps."""
    v, f = plane_grid(4)
    rng = np.random.default_rng(8)
    n = 2000
    angle = np.exp(rng.uniform(np.log(1e-7), np.log(1e-2), n))
    az = rng.uniform(0, 2 * np.pi, n)
    d = np.stack([np.cos(az) * np.cos(angle), -np.sin(angle), np.sin(az) * np.cos(angle)], 1)
    o = np.stack([rng.uniform(-1, 1, n), rng.uniform(0, 1e-3, n), rng.uniform(-1, 1, n)], 1)
    o, d = o.astype(np.float32), d.astype(np.float32)
    h = kernels.trace(kernels.build_bvh(v, f), o, d)
    check = check_closest(v, f, o, d, h.t, h.triangle)
    assert check.failures == 0, check.summary()
    assert (h.triangle >= 0).sum() > n // 10  # the case does exercise hits
