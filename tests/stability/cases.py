"""Stress inputs and a float64 oracle shared by the stability tests and
`benchmarks/stability.py` (so the published table and the suite check the same thing).

The oracle never trusts float32: every reference quantity is computed in float64 from the
exact float32 inputs. A ray that passes within rounding distance of a triangle's edge may
be decided either way by any float32 tracer, so the checks below separate *definite* hits
(the float64 ray crosses the triangle's interior by a clear margin) from *possible* ones.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh

F32_EPS = float(np.finfo(np.float32).eps)  # 2^-23
# Margin (see `pair_geometry`: distance from the ray to an edge over |vertex - origin|)
# inside which a float32 tracer may decide either way. Watertight float32 tests err by a
# few ulps (2^-23) of |vertex - origin|; 2^-14 leaves a factor of 500 of room, and a real
# traversal bug misses by whole triangles, far outside it.
BARY_TOL = 2.0**-14
# Largest relative t error accepted: the engine refines t in float64 and rounds once, so
# 2 float32 ulps (a bad refinement or an unrefined float32 t shows up far above this).
T_TOL = 2.0 * F32_EPS


# --- meshes ----------------------------------------------------------------------------


def icosphere(subdivisions: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """A closed unit icosphere centred at the origin (float64 vertices, int32 faces)."""
    s = trimesh.creation.icosphere(subdivisions=subdivisions)
    return np.asarray(s.vertices, np.float64), np.asarray(s.faces, np.int32)


def box_room(cells: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """A closed 2x1x1.5 box whose six walls are `cells` x `cells` grids of quads sharing
    their vertices (axis-aligned walls, T-junction free), centred at the origin."""
    ext = np.array([2.0, 1.0, 1.5])
    s = trimesh.creation.box(extents=ext)
    for _ in range(int(np.log2(cells))):
        s = s.subdivide()
    s.merge_vertices()
    return np.asarray(s.vertices, np.float64), np.asarray(s.faces, np.int32)


def torus(major: int = 24, minor: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """A closed torus (major radius 1, tube radius 0.35) in the xy plane, centred at 0."""
    s = trimesh.creation.torus(major_radius=1.0, minor_radius=0.35, major_sections=major,
                               minor_sections=minor)
    return np.asarray(s.vertices, np.float64), np.asarray(s.faces, np.int32)


def interior_points(name: str) -> np.ndarray:
    """Several points strictly inside each closed mesh (unit scale, centred at 0)."""
    if name == "torus":  # on and near the tube's core circle (radius 1, z = 0)
        a = np.array([0.0, 0.9, 2.1, 3.7, 5.3])
        r = np.array([1.0, 0.85, 1.1, 1.0, 0.95])
        z = np.array([0.0, 0.1, -0.15, 0.2, 0.0])
        return np.stack([r * np.cos(a), r * np.sin(a), z], axis=1)
    if name == "box_room":
        return np.array([[0.0, 0.0, 0.0], [0.7, 0.3, -0.5], [-0.9, -0.4, 0.6],
                         [0.25, -0.45, 0.05]])
    return np.array([[0.0, 0.0, 0.0], [0.3, 0.1, -0.2], [-0.5, 0.2, 0.1], [0.05, -0.6, 0.3]])


CLOSED_MESHES = {"icosphere": lambda: icosphere(3), "box_room": box_room, "torus": torus}


def transform(points: np.ndarray, scale: float, offset: float) -> np.ndarray:
    """points * scale + offset * (1, -1, 0.5), in float64 (round to float32 afterwards).
    The offset differs per axis so no coordinate is special."""
    return np.asarray(points, np.float64) * scale + offset * np.array([1.0, -1.0, 0.5])


def resolvable(scale: float, offset: float, extent: float = 2.0, ulps: float = 2.0**7) -> bool:
    """Whether a mesh `extent * scale` wide still spans `ulps` float32 ulps at `offset`."""
    far = abs(offset) * 1.5 + extent * scale
    return extent * scale >= ulps * float(np.spacing(np.float32(far)))


def watertight_case(name: str, scale: float = 1.0, offset: float = 0.0):
    """A closed mesh and rays from interior points aimed exactly at every vertex and every
    edge midpoint (float32 vertices, origins and directions; direction = target - origin,
    so t = 1 lands on the target)."""
    v64, f = CLOSED_MESHES[name]()
    v = transform(v64, scale, offset).astype(np.float32)
    edges = trimesh.geometry.faces_to_edges(f)
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    vd = v.astype(np.float64)
    targets = np.vstack([vd, 0.5 * (vd[edges[:, 0]] + vd[edges[:, 1]])])
    starts = transform(interior_points(name), scale, offset).astype(np.float32)
    o = np.repeat(starts, len(targets), axis=0)
    d = (np.tile(targets, (len(starts), 1)) - o).astype(np.float32)
    keep = np.any(d != 0, axis=1)  # an interior point never coincides with a target
    return v, f, o[keep], d[keep]


def plane_grid(n: int = 8, scale: float = 1.0, offset: float = 0.0, tilt: bool = False):
    """An open square plane (side 2 * scale) of n x n quads; y = 0 (or tilted about x by
    30 degrees) before the offset."""
    xs = np.linspace(-1.0, 1.0, n + 1)
    gx, gz = np.meshgrid(xs, xs, indexing="ij")
    p = np.stack([gx.ravel(), np.zeros(gx.size), gz.ravel()], axis=1)
    if tilt:
        c, s = np.cos(np.pi / 6), np.sin(np.pi / 6)
        p = p @ np.array([[1, 0, 0], [0, c, s], [0, -s, c]])
    f = []
    for i in range(n):
        for j in range(n):
            a, b = i * (n + 1) + j, (i + 1) * (n + 1) + j
            f += [[a, a + 1, b], [b, a + 1, b + 1]]
    return transform(p, scale, offset).astype(np.float32), np.array(f, np.int32)


def plane_normal(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    n = np.cross(v[f[0, 1]].astype(np.float64) - v[f[0, 0]], v[f[0, 2]].astype(np.float64)
                 - v[f[0, 0]])
    return n / np.linalg.norm(n)


def grazing_rays(v: np.ndarray, f: np.ndarray, count: int, seed: int = 0,
                 min_elevation: float = 1e-3):
    """Rays aimed at random points inside the plane from above, at elevations from
    `min_elevation` to 90 degrees (log-spaced, so grazing angles are well represented)."""
    rng = np.random.default_rng(seed)
    v64 = v.astype(np.float64)
    tri = rng.integers(0, len(f), count)
    w = rng.dirichlet([4.0, 4.0, 4.0], count)  # well inside each triangle
    p = np.einsum("rk,rkj->rj", w, v64[f[tri]])
    n = plane_normal(v, f)
    side = np.linalg.norm(v64.max(axis=0) - v64.min(axis=0))
    e1 = np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    elev = np.exp(rng.uniform(np.log(min_elevation), np.log(np.pi / 2), count))
    az = rng.uniform(0, 2 * np.pi, count)
    back = (np.cos(elev)[:, None] * (np.cos(az)[:, None] * e1 + np.sin(az)[:, None] * e2)
            + np.sin(elev)[:, None] * n)
    o = (p + 0.5 * side * back).astype(np.float32)
    d = (p - o.astype(np.float64)).astype(np.float32)
    # Rounding o and d to float32 can put a grazing ray under the plane; keep the rays
    # whose float32 form still definitely crosses the triangle they were aimed at.
    _, margin = pair_geometry(v, f, o, d, tri)
    keep = margin > BARY_TOL
    return o[keep], d[keep]


# --- the float64 oracle ------------------------------------------------------------------


def pair_geometry(v, f, o, d, tri=None):
    """float64 (t, margin) for rays against triangles: all pairs (R, M) when `tri` is None,
    else one triangle per ray (R,). t is the distance along d to the triangle's plane;
    margin is the signed distance, in the plane perpendicular to the ray, from the ray's
    line to the nearest edge (positive inside), divided by the largest |vertex - origin|.

    That normalisation matches how float32 tracers err: they work on vertex - origin, so
    their error is a few ulps of that length whatever the triangle's size or the angle
    (a barycentric margin would blow up for rays that graze a triangle's plane). Rays
    parallel to the plane, and degenerate triangles, get t = NaN and margin = -inf."""
    v64 = v.astype(np.float64)
    o64 = np.asarray(o, np.float64)
    d64 = np.asarray(d, np.float64)
    if tri is None:
        corners = [v64[f[:, k]][None] for k in range(3)]
        o64, d64 = o64[:, None], d64[:, None]
    else:
        corners = [v64[f[tri, k]] for k in range(3)]
    a, b, c = (x - o64 for x in corners)
    dd = np.sum(d64 * d64, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        sides = []
        for p, q in ((a, b), (b, c), (c, a)):
            side = np.sum(d64 * np.cross(p, q), axis=-1)  # Pluecker side of the ray
            e = q - p
            e_perp = e - d64 * (np.sum(e * d64, axis=-1) / dd)[..., None]
            length = np.sqrt(dd * np.sum(e_perp * e_perp, axis=-1))
            sides.append((side, length))
        det = sides[0][0] + sides[1][0] + sides[2][0]  # d . (twice the area normal)
        sign = np.sign(det)
        dist = [np.where(length > 0, sign * side / length, np.inf) for side, length in sides]
        reach = np.maximum(np.maximum(np.linalg.norm(a, axis=-1), np.linalg.norm(b, axis=-1)),
                           np.linalg.norm(c, axis=-1))
        margin = np.minimum(np.minimum(dist[0], dist[1]), dist[2]) / reach
        n = np.cross(corners[1] - corners[0], corners[2] - corners[0])
        t = np.sum(n * a, axis=-1) / np.sum(n * d64, axis=-1)
    bad = ~np.isfinite(t) | ~np.isfinite(margin) | (det == 0)
    return np.where(bad, np.nan, t), np.where(bad, -np.inf, margin)


@dataclass
class Check:
    """Outcome of checking one tracer's hits on one case."""

    rays: int = 0
    failures: int = 0  # escapes, wrong hit/miss, wrong triangle or t beyond T_TOL
    max_t_err: float = 0.0  # largest relative t error over rays whose hit was checked
    kinds: dict[str, int] = field(default_factory=dict)  # failure kind -> count

    def add(self, kind: str, mask: np.ndarray) -> None:
        n = int(np.count_nonzero(mask))
        if n:
            self.kinds[kind] = self.kinds.get(kind, 0) + n

    def merge(self, other: Check) -> Check:
        out = Check(self.rays + other.rays, self.failures + other.failures,
                    max(self.max_t_err, other.max_t_err), dict(self.kinds))
        for k, n in other.kinds.items():
            out.kinds[k] = out.kinds.get(k, 0) + n
        return out

    def summary(self) -> str:
        return f"{self.failures} of {self.rays} failed {self.kinds}, max t err {self.max_t_err:.3g}"


def t_error(t, t64, o, d) -> np.ndarray:
    """Relative error of reported t against the float64 plane distance t64. Where t64 is
    exactly 0 (the origin lies on the triangle) a relative error is undefined: the error is
    then the hit point's displacement |t| |d| relative to the origin's magnitude."""
    t = np.asarray(t, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.abs(t - t64) / np.abs(t64)
        scale = np.abs(np.asarray(o, np.float64)).max(axis=-1)
        at_origin = np.abs(t) * np.abs(np.asarray(d, np.float64)).max(axis=-1) / scale
    err = np.where(t64 == 0, np.where(scale > 0, at_origin, np.abs(t)), rel)
    return np.where(np.isnan(t64) | np.isnan(err), np.inf, err)


def check_reported(v, f, o, d, t, tri, check: Check, tmin=0.0, tmax=np.inf,
                   exact_t: bool = True) -> np.ndarray:
    """Check every reported hit against its own triangle in float64: the ray really passes
    through it (margin >= -BARY_TOL), t is in [tmin, tmax] and (with `exact_t`) within
    T_TOL of the float64 plane distance. Returns the per-ray failure mask (misses never
    fail here). Any-hit queries promise a t in range, not a refined one: exact_t=False."""
    hit = tri >= 0
    fail = np.zeros(len(o), dtype=bool)
    if not hit.any():
        return fail
    idx = np.flatnonzero(hit)
    t64, margin = pair_geometry(v, f, o[idx], d[idx], tri[idx])
    err = t_error(t[idx], t64, o[idx], d[idx])
    lo = np.broadcast_to(np.asarray(tmin, np.float64), (len(o),))[idx]
    hi = np.broadcast_to(np.asarray(tmax, np.float64), (len(o),))[idx]
    outside = margin < -BARY_TOL
    bad_t = (err > T_TOL) if exact_t else np.zeros(len(idx), dtype=bool)
    out_of_range = (t[idx] < lo) | (t[idx] > hi)
    check.add("hit_outside_triangle", outside)
    check.add("t_error", bad_t & ~outside)
    check.add("t_out_of_range", out_of_range)
    fail[idx] = outside | bad_t | out_of_range
    finite = np.isfinite(err)
    if finite.any():
        check.max_t_err = max(check.max_t_err, float(err[finite].max()))
    return fail


def check_closest(v, f, o, d, t, tri, tmin=0.0, tmax=np.inf, any_hit=False,
                  chunk: int = 256, exact_t: bool = True) -> Check:
    """Full check against the all-pairs float64 oracle (small inputs only): a ray misses
    only if no triangle is definitely hit in range; a reported hit is on a possible
    triangle with the right t; a closest hit is no farther than any definite hit."""
    check = Check(rays=len(o))
    fail = check_reported(v, f, o, d, t, tri, check, tmin, tmax,
                          exact_t=exact_t and not any_hit)
    r = len(o)
    lo = np.broadcast_to(np.asarray(tmin, np.float64), (r,))
    hi = np.broadcast_to(np.asarray(tmax, np.float64), (r,))
    for s in range(0, r, chunk):
        e = min(r, s + chunk)
        t64, margin = pair_geometry(v, f, o[s:e], d[s:e])
        span = np.maximum(np.abs(t64), 1e-300) * 1e-5  # keep ties at tmin/tmax ambiguous
        inside = (t64 > lo[s:e, None] + span) & (t64 < hi[s:e, None] - span)
        definite = (margin > BARY_TOL) & inside
        first = np.where(definite, t64, np.inf).min(axis=1)
        missed = (tri[s:e] < 0) & np.isfinite(first)
        check.add("missed_definite_hit", missed)
        fail[s:e] |= missed
        if not any_hit:
            farther = (tri[s:e] >= 0) & (t[s:e].astype(np.float64) > first * (1 + 1e-6))
            check.add("not_closest", farther)
            fail[s:e] |= farther
    check.failures = int(np.count_nonzero(fail))
    return check


def check_escapes(v, f, o, d, t, tri, exact_t: bool = True) -> Check:
    """Watertightness: every ray starts inside a closed mesh, so every ray must hit, on a
    triangle it really passes through, with the right t (`exact_t`: within T_TOL; a
    peer without float64 refinement is judged on hits alone, its t error reported)."""
    check = Check(rays=len(o))
    escaped = tri < 0
    check.add("escaped", escaped)
    fail = check_reported(v, f, o, d, t, tri, check, exact_t=exact_t) | escaped
    check.failures = int(np.count_nonzero(fail))
    return check


# --- the engine's tracers, one signature ----------------------------------------------------


def engine_tracers() -> dict:
    """name -> trace(v, f, o, d, tmin, tmax, any_hit) -> (t, triangle) for every engine
    path: the BVH with both builders, and DACRT's variants where the engine has them."""
    from scenesort import kernels

    def bvh(method: str, leaf_size: int):
        def run(v, f, o, d, tmin=0.0, tmax=np.inf, any_hit=False):
            h = kernels.trace(kernels.build_bvh(v, f, method=method, leaf_size=leaf_size),
                              o, d, tmin=tmin, tmax=tmax, any_hit=any_hit)
            return h.t, h.triangle
        return run

    def dacrt(variant: str):
        def run(v, f, o, d, tmin=0.0, tmax=np.inf, any_hit=False):
            h = kernels.dacrt_trace(v, f, o, d, tmin=tmin, tmax=tmax, variant=variant)
            return h.t, h.triangle
        return run

    out = {"bvh_sah": bvh("sah", 8), "bvh_median_leaf1": bvh("median", 1)}
    if hasattr(kernels, "dacrt_trace"):
        out["dacrt_pool"] = dacrt("pool")
        out["dacrt_breadth_first"] = dacrt("breadth_first")
    return out


def mixed_scene(seed: int = 0, scale: float = 1.0, offset: float = 0.0):
    """An icosphere (320 triangles) standing on a 6x6 floor grid, plus 150 random small
    triangles around it: closed, open, shared-edge and isolated geometry in one scene."""
    rng = np.random.default_rng(seed)
    sv, sf = icosphere(2)
    sv = sv * 0.5 + [0.0, 0.5, 0.0]
    gv, gf = plane_grid(6)
    gv = gv.astype(np.float64) * 1.5
    centres = rng.uniform(-1.2, 1.2, (150, 1, 3)) * [1.0, 0.6, 1.0] + [0.0, 0.6, 0.0]
    tv = (centres + rng.normal(scale=0.08, size=(150, 3, 3))).reshape(-1, 3)
    tf = np.arange(len(tv)).reshape(-1, 3)
    v = np.vstack([sv, gv, tv])
    f = np.vstack([sf, gf + len(sv), tf + len(sv) + len(gv)]).astype(np.int32)
    return transform(v, scale, offset).astype(np.float32), f


def huge_over_tiny(tiny: int, seed: int = 9):
    """One 2e4-wide triangle over `tiny` triangles of size 1e-5 (extents 1e9 apart), and
    rays: straight down at 599 tiny triangles' centroids, and 600 random ones. Returns
    (v, f, o, d), float32 and int32."""
    rng = np.random.default_rng(seed)
    huge = np.array([[-1e4, 0, -1e4], [1e4, 0, -1e4], [0, 0, 2e4]])
    centres = rng.uniform(-1, 1, (tiny, 1, 3)) * [1, 0.01, 1] + [0, 0.02, 0]
    small = (centres + rng.normal(scale=1e-5, size=(tiny, 3, 3))).reshape(-1, 3)
    v = np.vstack([huge, small]).astype(np.float32)
    f = np.arange(len(v), dtype=np.int32).reshape(-1, 3)
    cen = v[f[1:600]].astype(np.float64).mean(axis=1)
    o = np.vstack([cen + [0, 1, 0], rng.uniform(-2, 2, (600, 3))]).astype(np.float32)
    d = np.vstack([np.tile([[0, -1, 0]], (599, 1)), rng.normal(size=(600, 3))])
    return v, f, o, d.astype(np.float32)


def scene_rays(v, f, count: int, seed: int = 0):
    """Half aimed at random points of random triangles (vertices and edges included),
    half in random directions, all from random points in the scene's box enlarged 1.5x."""
    rng = np.random.default_rng(seed)
    v64 = v.astype(np.float64)
    lo, hi = v64.min(axis=0), v64.max(axis=0)
    mid, half = 0.5 * (lo + hi), 0.75 * (hi - lo)
    o = (mid + half * rng.uniform(-1, 1, (count, 3))).astype(np.float32)
    k = count // 2
    tri = rng.integers(0, len(f), k)
    w = rng.dirichlet([1.0, 1.0, 1.0], k)
    w[: k // 4] = np.eye(3)[rng.integers(0, 3, k // 4)]  # exactly at a vertex
    w[k // 4 : k // 2] = [0.5, 0.5, 0.0]  # an edge midpoint
    target = np.einsum("rk,rkj->rj", w, v64[f[tri]])
    d = np.empty((count, 3))
    d[:k] = target - o[:k]
    d[k:] = rng.normal(size=(count - k, 3))
    d = d.astype(np.float32)
    ok = np.any(d != 0, axis=1)
    return o[ok], d[ok]
