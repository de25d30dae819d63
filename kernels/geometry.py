"""Rays, boxes and triangles: the watertight ray/triangle test and a conservative slab test.

Guarantees (float32 input, no fast-math):
- `intersect_triangle` is watertight in the sense of Woop, Benthin and Wald (JCGT 2013): a ray
  through a shared edge or vertex of a closed mesh hits at least one of the triangles that
  share it. Edge functions that round to exactly zero are recomputed in float64, as the
  paper recommends. Degenerate (zero-area) triangles never hit.
- `intersect_box` never misses a box that the exact ray touches (Ize 2013's 1 + 2*gamma(3)
  widening of the far distance); rays with zero direction components and origins on a box
  face are handled exactly (no 0 * inf NaN).
"""

from __future__ import annotations

import warp as wp

# gamma(3) = 3 eps / (1 - 3 eps) with eps = 2^-24 (Pharr, Jakob, Humphreys, PBR 3.9.1).
FAR_WIDEN = wp.constant(1.0 + 2.0 * 1.7881397e-07)
INF = wp.constant(float("inf"))


@wp.struct
class Ray:
    """A ray with what both tests precompute from it."""

    origin: wp.vec3
    inv_dir: wp.vec3  # 1/d, +inf where d == 0 (sign dropped: see intersect_box)
    zero_axis: wp.vec3i  # 1 where d == 0 exactly
    any_zero: int  # 1 if some component of d is 0: the slab test then takes the careful path
    kx: int  # Woop's axis permutation: kz is the dominant axis of d
    ky: int
    kz: int
    shear: wp.vec3  # (Sx, Sy, Sz) = (dx/dz, dy/dz, 1/dz) in the permuted frame
    direction: wp.vec3


@wp.struct
class Hit:
    t: float  # inf on a miss
    triangle: int  # -1 on a miss
    u: float  # barycentric weight of v1 (Embree's convention)
    v: float  # barycentric weight of v2


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
def make_ray(origin: wp.vec3, d: wp.vec3) -> Ray:
    r = Ray()
    r.origin = origin
    r.direction = d
    ad = wp.vec3(wp.abs(d[0]), wp.abs(d[1]), wp.abs(d[2]))
    kz = int(0)
    if ad[1] > ad[kz]:
        kz = 1
    if ad[2] > ad[kz]:
        kz = 2
    kx = (kz + 1) % 3
    ky = (kx + 1) % 3
    if d[kz] < 0.0:  # keep the winding so that U, V, W have one sign for a front or back hit
        tmp = kx
        kx = ky
        ky = tmp
    r.kx = kx
    r.ky = ky
    r.kz = kz
    r.shear = wp.vec3(d[kx] / d[kz], d[ky] / d[kz], 1.0 / d[kz])
    inv = wp.vec3(INF, INF, INF)
    zero = wp.vec3i(1, 1, 1)
    for k in range(3):
        if d[k] != 0.0:
            inv[k] = 1.0 / d[k]
            zero[k] = 0
    r.inv_dir = inv
    r.zero_axis = zero
    r.any_zero = wp.max(wp.max(zero[0], zero[1]), zero[2])
    return r


@wp.func
def intersect_box(r: Ray, lo: wp.vec3, hi: wp.vec3, tmin: float, tmax: float) -> float:
    """Entry distance of the ray into [lo, hi] clipped to [tmin, tmax], or inf if it misses."""
    if r.any_zero == 0:  # no zero direction component: no NaN can arise below
        ta = wp.cw_mul(lo - r.origin, r.inv_dir)
        tb = wp.cw_mul(hi - r.origin, r.inv_dir)
        near = min3(ta, tb)
        far = max3(ta, tb)
        t0 = wp.where(near[0] > tmin, near[0], tmin)
        t0 = wp.where(near[1] > t0, near[1], t0)
        t0 = wp.where(near[2] > t0, near[2], t0)
        t1 = wp.where(far[0] < far[1], far[0], far[1])
        t1 = wp.where(far[2] < t1, far[2], t1) * FAR_WIDEN
        t1 = wp.where(tmax < t1, tmax, t1)
        if t0 <= t1:
            return t0
        return INF
    t0 = tmin
    t1 = tmax
    for k in range(3):
        if r.zero_axis[k] != 0:
            # Parallel to this slab: inside (faces included) or never.
            if r.origin[k] < lo[k] or r.origin[k] > hi[k]:
                return INF
        else:
            a = (lo[k] - r.origin[k]) * r.inv_dir[k]
            b = (hi[k] - r.origin[k]) * r.inv_dir[k]
            enter = wp.where(a < b, a, b)
            leave = wp.where(a < b, b, a) * FAR_WIDEN
            t0 = wp.where(enter > t0, enter, t0)
            t1 = wp.where(leave < t1, leave, t1)
    if t0 <= t1:
        return t0
    return INF


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
