"""Scale and offset sweep: the same scenes scaled by 1e-4 .. 1e4 and moved up to 1e6 away
from the origin must trace exactly as the float64 oracle says, and AO of surfaces that
cannot occlude themselves must stay exactly 1.0 (no self-intersection speckles)."""

from __future__ import annotations

import numpy as np
import pytest

from scenesort import kernels

from .cases import (
    check_closest,
    grazing_rays,
    icosphere,
    mixed_scene,
    plane_grid,
    resolvable,
    scene_rays,
    transform,
)
from .test_watertightness import SWEEP


@pytest.mark.parametrize(("scale", "offset"), SWEEP)
def test_closest_and_any_hit_agree_with_float64(scale, offset):
    """Guards against precision loss that grows with scale or distance from the origin
    (a hit/miss flip away from edges, a farther triangle returned, t off by more than
    2 ulps): rays at vertices, edge midpoints, interiors and random directions."""
    v, f = mixed_scene(0, scale, offset)
    o, d = scene_rays(v, f, 2000, seed=1)
    bvh = kernels.build_bvh(v, f)
    h = kernels.trace(bvh, o, d)
    check = check_closest(v, f, o, d, h.t, h.triangle)
    assert check.failures == 0, check.summary()
    assert check.max_t_err > 0  # the check did compare some hits
    a = kernels.trace(bvh, o, d, any_hit=True)
    check = check_closest(v, f, o, d, a.t, a.triangle, any_hit=True)
    assert check.failures == 0, check.summary()


@pytest.mark.parametrize(("scale", "offset"), [(1e-2, 1e2), (10.0, 1e6)])
def test_per_ray_ranges_agree_with_float64(scale, offset):
    """Guards the [tmin, tmax] clipping far from the origin: a hit just inside the range
    must be kept and one outside dropped, as the float64 oracle decides."""
    v, f = mixed_scene(3, scale, offset)
    o, d = scene_rays(v, f, 1500, seed=4)
    rng = np.random.default_rng(5)
    tmin = (rng.random(len(o)) * 0.5).astype(np.float32)
    tmax = (tmin + rng.random(len(o)) * 0.7).astype(np.float32)
    h = kernels.trace(kernels.build_bvh(v, f), o, d, tmin=tmin, tmax=tmax)
    check = check_closest(v, f, o, d, h.t, h.triangle, tmin, tmax)
    assert check.failures == 0, check.summary()


def test_reported_t_is_never_below_tmin_when_origin_is_on_the_triangle():
    """Guards the float64 refinement of t: a ray starting exactly on a triangle hits it at
    t = 0, and the refined t must not drop below tmin = 0 (it came back as -4.6e-22, out of
    the [tmin, tmax] the contract promises). Smallest input found by the sweep above."""
    v = np.array([[100.00015258789062, -100.0, 50.00004959106445],
                  [100.0000991821289, -100.0, 50.000099182128906],
                  [100.00015258789062, -100.0, 50.000099182128906]], np.float32)
    f = np.array([[0, 1, 2]], np.int32)
    o = np.array([[100.00011444091797, -100.0, 50.000091552734375]], np.float32)
    d = np.array([[1.5084872245788574, -0.6466293931007385, 1.3039276599884033]], np.float32)
    h = kernels.trace(kernels.build_bvh(v, f), o, d)
    assert h.triangle[0] == 0
    assert h.t[0] >= 0.0, f"t = {h.t[0]!r} < tmin = 0"


@pytest.mark.parametrize("tilt", [False, True], ids=["axis_plane", "tilted_plane"])
@pytest.mark.parametrize(("scale", "offset"), SWEEP)
def test_open_plane_ao_is_exactly_one(scale, offset, tilt):
    """Guards the occlusion-ray spawn offset: an open plane can occlude nothing, so AO must
    be exactly 1.0 for every pixel, including primary rays at grazing angles down to 1e-4
    rad (where a too-small offset gives black speckles) and at every scale and offset."""
    v, f = plane_grid(16, scale, offset, tilt)
    o, d = grazing_rays(v, f, 1500, seed=2, min_elevation=1e-4)
    bvh = kernels.build_bvh(v, f)
    assert np.all(kernels.trace(bvh, o, d).triangle >= 0)  # every pixel is on the plane
    ao = kernels.ambient_occlusion(bvh, o, d, spp=16)
    assert np.all(ao == 1.0), f"{int((ao < 1).sum())} of {len(ao)} pixels darker (min {ao.min()})"


@pytest.mark.parametrize(("scale", "offset"), [(1e-4, 0.0), (1.0, 1e4), (10.0, 1e6)])
def test_convex_object_ao_is_exactly_one_at_the_silhouette(scale, offset):
    """Guards against self-occlusion on curved, tessellated surfaces: a convex icosphere
    cannot occlude itself, yet primary rays that graze its silhouette hit it at angles
    where occlusion rays start nearly tangent to the neighbouring triangles."""
    sv, sf = icosphere(3)
    v = transform(sv, scale, offset).astype(np.float32)
    centre = transform(np.zeros((1, 3)), scale, offset)[0]
    rng = np.random.default_rng(6)
    # Camera 4 radii away on random sides, aimed at points just inside the silhouette.
    cam = rng.normal(size=(1200, 3))
    cam /= np.linalg.norm(cam, axis=1, keepdims=True)
    side = np.cross(cam, rng.normal(size=(1200, 3)))
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    reach = 0.95 + 0.05 * rng.random((1200, 1)) ** 3  # bunched towards the rim
    o = (centre + 4.0 * scale * cam).astype(np.float32)
    target = centre + scale * reach * side
    d = (target - o.astype(np.float64)).astype(np.float32)
    bvh = kernels.build_bvh(v, sf)
    hit = kernels.trace(bvh, o, d).triangle >= 0
    assert hit.sum() > 1000
    ao = kernels.ambient_occlusion(bvh, o[hit], d[hit], spp=16)
    assert np.all(ao == 1.0), f"{int((ao < 1).sum())} of {len(ao)} pixels darker (min {ao.min()})"


def test_unresolvable_offsets_fail_gracefully():
    """Guards the far end where float32 cannot resolve the scene (a 2e-4 wide scene at
    1e2, a 2-unit one at 1e6: under 128 ulps wide): no crash, no NaN, every reported hit
    on a triangle in range and t >= 0 up to the t = 0 ties (origins rounded onto surfaces)."""
    for scale, offset in [(1e-4, 1e2), (1.0, 1e6)]:
        assert not resolvable(scale, offset)
        v, f = mixed_scene(0, scale, offset)
        o, d = scene_rays(v, f, 1500, seed=1)
        h = kernels.trace(kernels.build_bvh(v, f), o, d)
        hit = h.triangle >= 0
        assert not np.isnan(h.t).any()
        assert np.all(np.isinf(h.t[~hit])) and np.all(h.triangle[hit] < len(f))
        assert np.all(h.t[hit] >= -1e-12 * np.abs(o[hit]).max())
