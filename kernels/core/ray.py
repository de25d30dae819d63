"""Rays and the conservative ray/box slab test.

Guarantee (float32 input, no fast-math): `intersect_box` never misses a box that the exact
ray touches (Ize 2013's 1 + 2*gamma(3) widening of the far distance); rays with zero
direction components and origins on a box face are handled exactly (no 0 * inf NaN).
"""

from __future__ import annotations

import warp as wp

from .box import INF, max3, min3

# gamma(3) = 3 eps / (1 - 3 eps) with eps = 2^-24 (Pharr, Jakob, Humphreys, PBR 3.9.1).
FAR_WIDEN = wp.constant(1.0 + 2.0 * 1.7881397e-07)


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
def no_hit(h: wp.ref[Hit]):
    """Make h a miss: t inf, triangle -1."""
    h.t = INF
    h.triangle = -1


@wp.func
def hit_distance(h: Hit) -> float:
    return h.t


@wp.func
def valid_ray(o: wp.vec3, d: wp.vec3) -> bool:
    """What validate.as_rays accepts: a finite origin and a finite, non-zero direction."""
    return wp.isfinite(o) and wp.isfinite(d) and (d[0] != 0.0 or d[1] != 0.0 or d[2] != 0.0)


# flag_invalid_rays's loop on a CPU: the floats compared as the compiler vectorises them
# (x - x == 0 only where x is finite), a third of Warp's loop's time per ray.
CHECK_SOURCE = """
#if !defined(__CUDA_ARCH__)
    if (origins.strides[0] != 12 || directions.strides[0] != 12)
        return -1;
    const float* o = (const float*)origins.data + 3 * (long long)first;
    const float* d = (const float*)directions.data + 3 * (long long)first;
    const int n = last - first;
    int ok = 1;
    for (int i = 0; i < 3 * n; ++i)
        ok &= (o[i] - o[i] == 0.0f) & (d[i] - d[i] == 0.0f);
    for (int i = 0; i < n; ++i)
        ok &= (d[3 * i] != 0.0f) | (d[3 * i + 1] != 0.0f) | (d[3 * i + 2] != 0.0f);
    return ok;
#else
    return -1;
#endif
"""


@wp.func_native(CHECK_SOURCE)
def rays_valid_native(origins: wp.array(dtype=wp.vec3), directions: wp.array(dtype=wp.vec3),
                      first: int, last: int) -> int:
    """1 if rays [first, last) are all valid_ray's, else 0; -1 where not compiled (CUDA) or
    the arrays are strided."""
    ...


@wp.func
def flag_invalid_rays(origins: wp.array(dtype=wp.vec3), directions: wp.array(dtype=wp.vec3),
                      first: int, last: int, invalid: wp.array(dtype=int)):
    """invalid[0] = 1 where a ray of [first, last) is one as_rays refuses: the kernels that
    trace the caller's rays check them as they first read them (one pass over a chunk
    that then stays in cache), and the caller raises as_rays's error after the launch
    (validate.refuse_flagged_rays). Read in Python first, 10k rays cost ~70 us out of
    cache, a fifth of a 10k-ray call on two threads."""
    ok = rays_valid_native(origins, directions, first, last)
    if ok == 0:
        invalid[0] = 1
    elif ok < 0:
        for i in range(first, last):
            if not valid_ray(origins[i], directions[i]):
                invalid[0] = 1


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
def per_ray(values: wp.array(dtype=float), i: int) -> float:
    """Ray i's value of an array with one value per ray or one for all: a min, not the
    modulo it replaces (an integer division per ray, 1-4% of an any-hit ray's time)."""
    return values[wp.min(i, values.shape[0] - 1)]


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
