"""Axis-aligned boxes: componentwise bounds, surface area, the longest axis and the spatial
median plane that halves it (the split of the 2012 paper's median builder and DACRT, and
of the 2013 paper).

Boxes are (lo, hi) pairs of `wp.vec3`; an empty box is (+inf, -inf), which every min/max
update fixes at its first point.
"""

from __future__ import annotations

import warp as wp

INF = wp.constant(float("inf"))


@wp.func
def min3(a: wp.vec3, b: wp.vec3) -> wp.vec3:
    """Componentwise minimum of NaN-free vectors: a plain select (wp.min also handles NaN,
    at three times the instructions on CPU)."""
    return wp.vec3(wp.where(a[0] < b[0], a[0], b[0]), wp.where(a[1] < b[1], a[1], b[1]),
                   wp.where(a[2] < b[2], a[2], b[2]))


@wp.func
def max3(a: wp.vec3, b: wp.vec3) -> wp.vec3:
    """Componentwise maximum of NaN-free vectors (see min3)."""
    return wp.vec3(wp.where(a[0] > b[0], a[0], b[0]), wp.where(a[1] > b[1], a[1], b[1]),
                   wp.where(a[2] > b[2], a[2], b[2]))


@wp.func
def longest_axis(lo: wp.vec3, hi: wp.vec3) -> int:
    e = hi - lo
    axis = int(0)
    if e[1] > e[axis]:
        axis = 1
    if e[2] > e[axis]:
        axis = 2
    return axis


@wp.func
def half_area(lo: wp.vec3, hi: wp.vec3) -> float:
    e = max3(hi - lo, wp.vec3(0.0))
    return e[0] * e[1] + e[1] * e[2] + e[2] * e[0]


@wp.func
def median_plane(lo: wp.vec3, hi: wp.vec3) -> wp.vec2:
    """(axis, position) of the spatial median: the middle of the box's longest axis."""
    axis = longest_axis(lo, hi)
    return wp.vec2(float(axis), 0.5 * (lo[axis] + hi[axis]))
