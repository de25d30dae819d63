"""Triangles: the watertight ray/triangle test, the float64 refinement of a hit, and the
zero-area test.

Guarantees (float32 input, no fast-math): `intersect_triangle` is watertight in the sense of
Woop, Benthin and Wald (JCGT 2013): a ray through a shared edge or vertex of a closed mesh
hits at least one of the triangles that share it. Edge functions that round to exactly zero
are recomputed in float64, as the paper recommends. Degenerate (zero-area) triangles never
hit.
"""

from __future__ import annotations

import warp as wp

from .box import INF
from .ray import Ray


@wp.func
def edge_function(ax: float, ay: float, bx: float, by: float) -> float:
    """Signed double area of (0, a, b); recomputed in float64 when float32 rounds it to zero."""
    e = bx * ay - by * ax
    if e == 0.0:
        e = float(wp.float64(bx) * wp.float64(ay) - wp.float64(by) * wp.float64(ax))
    return e


@wp.func(inline=True)  # the hot loop of every tracer; clang's heuristic sometimes declines
def intersect_triangle(
    r: Ray, v0: wp.vec3, v1: wp.vec3, v2: wp.vec3, tmin: float, tmax: float
) -> wp.vec3:
    """Woop, Benthin and Wald 2013 (sec. 4): returns (t, u, v); t = inf on a miss or outside
    [tmin, tmax]."""
    a = v0 - r.origin
    b = v1 - r.origin
    c = v2 - r.origin
    sx = r.shear[0]
    sy = r.shear[1]
    sz = r.shear[2]
    ax = a[r.kx] - sx * a[r.kz]
    ay = a[r.ky] - sy * a[r.kz]
    bx = b[r.kx] - sx * b[r.kz]
    by = b[r.ky] - sy * b[r.kz]
    cx = c[r.kx] - sx * c[r.kz]
    cy = c[r.ky] - sy * c[r.kz]
    u = edge_function(bx, by, cx, cy)
    v = edge_function(cx, cy, ax, ay)
    w = edge_function(ax, ay, bx, by)
    miss = wp.vec3(INF, 0.0, 0.0)
    if (u < 0.0 or v < 0.0 or w < 0.0) and (u > 0.0 or v > 0.0 or w > 0.0):
        return miss
    det = u + v + w
    if det == 0.0:
        return miss
    t_scaled = u * (sz * a[r.kz]) + v * (sz * b[r.kz]) + w * (sz * c[r.kz])
    inv_det = 1.0 / det
    t = t_scaled * inv_det
    if not (t >= tmin and t <= tmax):  # also rejects a NaN from overflowing coordinates
        return miss
    return wp.vec3(t, v * inv_det, w * inv_det)


@wp.func
def refine_hit(r: Ray, v0: wp.vec3, v1: wp.vec3, v2: wp.vec3, tmin: float, tmax: float,
               found: wp.vec3) -> wp.vec3:
    """(t, u, v) of a hit that `intersect_triangle` found (`found`) recomputed in float64
    with the same projection, so that t is correct to float32 rounding even when the hit is
    close to the origin (the float32 test decides hit or miss; this only sharpens the
    reported distance). The refined t is clamped to [tmin, tmax], the range the float32
    test accepted: a ray that starts on the triangle could otherwise report t < tmin. Where
    float64 finds no hit (a sliver only float32 rounding hit), `found` is kept."""
    ox = wp.float64(r.origin[r.kx])
    oy = wp.float64(r.origin[r.ky])
    oz = wp.float64(r.origin[r.kz])
    dz = wp.float64(r.direction[r.kz])
    sx = wp.float64(r.direction[r.kx]) / dz
    sy = wp.float64(r.direction[r.ky]) / dz
    az = wp.float64(v0[r.kz]) - oz
    bz = wp.float64(v1[r.kz]) - oz
    cz = wp.float64(v2[r.kz]) - oz
    ax = wp.float64(v0[r.kx]) - ox - sx * az
    ay = wp.float64(v0[r.ky]) - oy - sy * az
    bx = wp.float64(v1[r.kx]) - ox - sx * bz
    by = wp.float64(v1[r.ky]) - oy - sy * bz
    cx = wp.float64(v2[r.kx]) - ox - sx * cz
    cy = wp.float64(v2[r.ky]) - oy - sy * cz
    u = cx * by - cy * bx
    v = ax * cy - ay * cx
    w = bx * ay - by * ax
    det = u + v + w
    if det == wp.float64(0.0):
        return found
    t = (u * az + v * bz + w * cz) / (det * dz)
    return wp.vec3(wp.clamp(float(t), tmin, tmax), float(v / det), float(w / det))


@wp.func
def is_degenerate(a: wp.vec3, b: wp.vec3, c: wp.vec3) -> bool:
    """Zero area: the float64 cross product of the float32 edges is exactly zero."""
    a64 = wp.vec3d(wp.float64(a[0]), wp.float64(a[1]), wp.float64(a[2]))
    e1 = wp.vec3d(wp.float64(b[0]), wp.float64(b[1]), wp.float64(b[2])) - a64
    e2 = wp.vec3d(wp.float64(c[0]), wp.float64(c[1]), wp.float64(c[2])) - a64
    n = wp.cross(e1, e2)
    zero = wp.float64(0.0)
    return n[0] == zero and n[1] == zero and n[2] == zero
