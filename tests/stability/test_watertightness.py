"""Watertightness: rays from inside closed meshes, aimed exactly at every vertex and every
edge midpoint (where a non-watertight test lets rays slip between triangles), must all hit,
at any scale and offset that float32 can still resolve."""

from __future__ import annotations

import numpy as np
import pytest

from scenesort import kernels

from .cases import (
    CLOSED_MESHES,
    check_closest,
    check_escapes,
    engine_tracers,
    resolvable,
    watertight_case,
)

# (scale, offset): test_trace.py covers a few for the icosphere; these add the box room,
# the torus, the small-scale/large-offset corner and the 1e6 offset.
SWEEP = [(1.0, 0.0), (1e-4, 0.0), (1e4, 0.0), (1e-2, 1e2), (1.0, 1e4), (1e3, 1e5), (10.0, 1e6)]


def test_sweep_is_resolvable():
    """Guards the sweep itself: every case keeps the mesh at least 128 float32 ulps wide,
    so a failure below is the tracer's, not a mesh collapsed by rounding."""
    assert all(resolvable(s, o) for s, o in SWEEP)


@pytest.mark.parametrize("name", sorted(CLOSED_MESHES))
@pytest.mark.parametrize(("scale", "offset"), SWEEP)
def test_no_ray_escapes_closed_mesh(name, scale, offset):
    """Guards against rays slipping through shared edges and vertices (a non-watertight
    triangle test or a box test that drops a node the ray grazes), and against wrong t:
    every hit is on a triangle the float64 ray passes through, t within 2 ulps."""
    v, f, o, d = watertight_case(name, scale, offset)
    bvh = kernels.build_bvh(v, f)
    h = kernels.trace(bvh, o, d)
    check = check_escapes(v, f, o, d, h.t, h.triangle)
    assert check.failures == 0, check.summary()
    occluded = kernels.trace(bvh, o, d, any_hit=True)
    assert np.all(occluded.triangle >= 0), f"{int((occluded.triangle < 0).sum())} any-hit escapes"


@pytest.mark.parametrize("name", ["torus", "box_room"])
def test_nonconvex_closest_hit_against_float64(name):
    """Guards against the traversal returning a farther wall than the first one crossed
    (the torus is not convex: a ray to a far vertex crosses the tube twice), checked
    against the all-pairs float64 oracle."""
    v, f, o, d = watertight_case(name, 1e2, 1e3)
    h = kernels.trace(kernels.build_bvh(v, f, method="median", leaf_size=1), o, d)
    check = check_closest(v, f, o, d, h.t, h.triangle)
    assert check.failures == 0, check.summary()


@pytest.mark.parametrize("engine", sorted(engine_tracers()))
def test_every_engine_is_watertight(engine):
    """Guards each engine path (both BVH builders, DACRT where present) separately: a
    watertight triangle test is wasted if one traversal drops rays on shared edges."""
    run = engine_tracers()[engine]
    for name in sorted(CLOSED_MESHES):
        v, f, o, d = watertight_case(name, 3.0, -50.0)
        t, tri = run(v, f, o, d)
        check = check_escapes(v, f, o, d, t, tri)
        assert check.failures == 0, f"{name}: {check.summary()}"
