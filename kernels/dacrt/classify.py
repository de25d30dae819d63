"""Rays and triangles against a node box and a split plane, as both DACRT variants classify
them: left, straddling or right of the plane within the box, or clipped (sec. 5.2, PPS1)."""

from __future__ import annotations

import warp as wp

from ..core.box import INF
from .records import RayRecord

T_WIDEN = wp.constant(1.0e-5)  # relative widening of [tmin, tmax] for classification

# element classes (ray_cls / tri_cls)
CLS_LEFT = wp.constant(0)
CLS_STRADDLE = wp.constant(1)
CLS_RIGHT = wp.constant(2)
CLS_CLIPPED = wp.constant(3)


@wp.func
def widen(lo: wp.vec3, hi: wp.vec3, m: float) -> wp.mat33:
    """Rows 0, 1: the box grown by m on every side."""
    return wp.matrix_from_rows(lo - wp.vec3(m), hi + wp.vec3(m), wp.vec3(0.0))


@wp.func
def infinite(x: float) -> bool:
    """wp.isinf compiles to a libm call on CPU (spilling every register around it)."""
    return wp.abs(x) == INF


@wp.func
def ray_span(r: RayRecord, lo: wp.vec3, hi: wp.vec3, tmin: float, tmax: float) -> wp.vec2:
    """(entry, exit) of the ray in [lo, hi] within [tmin, tmax]; entry inf on a miss."""
    t0 = tmin
    t1 = tmax
    for k in range(3):
        if infinite(r.inv_dir[k]):
            if r.origin[k] < lo[k] or r.origin[k] > hi[k]:
                return wp.vec2(INF, INF)
        else:
            a = (lo[k] - r.origin[k]) * r.inv_dir[k]
            b = (hi[k] - r.origin[k]) * r.inv_dir[k]
            enter = wp.where(a < b, a, b)  # selects, not wp.min: a third of the instructions
            leave = wp.where(a < b, b, a)
            t0 = wp.where(enter > t0, enter, t0)
            t1 = wp.where(leave < t1, leave, t1)
    if t0 <= t1:
        return wp.vec2(t0, t1)
    return wp.vec2(INF, INF)


@wp.func
def widened_range(r: RayRecord) -> wp.vec2:
    lo = r.tmin
    hi = r.tmax
    return wp.vec2(lo - T_WIDEN * wp.abs(lo), hi + T_WIDEN * wp.abs(hi))


@wp.func
def ray_side(r: RayRecord, span: wp.vec2, axis: int, split: float, m: float) -> int:
    """Side of the plane (widened by m) that the ray's points within the span lie on,
    compared in t: the plane's crossings (split -+ m - o) / d against the span's ends, so no
    division (the rounding of the products is a few ulps of t: far inside the margin)."""
    inv = r.inv_dir[axis]
    o = r.origin[axis]
    if infinite(inv):
        return side_of(wp.vec2(o, o), split, m)
    below = (split - m - o) * inv  # t where the ray crosses split - m
    above = (split + m - o) * inv
    if inv > 0.0:
        return CLS_STRADDLE + int(span[0] > above) - int(span[1] < below)
    return CLS_STRADDLE + int(span[1] < above) - int(span[0] > below)


@wp.func
def side_of(lo_hi: wp.vec2, split: float, m: float) -> int:
    if lo_hi[1] < split - m:
        return CLS_LEFT
    if lo_hi[0] > split + m:
        return CLS_RIGHT
    return CLS_STRADDLE
