"""Ambient occlusion per primary ray, with fixed or adaptive sample counts.

Definition (issue 4; Cycles' AO pass since issue 14): for a primary ray's closest hit p
with shading normal n, AO(p) = (1/pi) * integral over the hemisphere around n of
V(p, w) cos(theta) dw, where V = 1 when no triangle lies within `distance` along w. It is
estimated with cosine-weighted directions, so each sample is V itself (0 or 1) and the
estimate is the fraction of unoccluded occlusion rays. A primary ray that misses gets 1.0.

The shading normal is the geometric normal ng turned toward the ray's origin, or with
`normals=` (one per triangle corner, as Blender's `Mesh.corner_normals`) the corners
interpolated at p (Cycles' `triangle_smooth_normal`), flipped with ng on a back face
(`shader_setup_from_ray`). As in Cycles' `integrate_surface_ao`, every direction of the
hemisphere about n is traced, also those below the triangle's plane (dot(ng, w) <= 0,
possible where n differs from ng): they start on the viewer's side and count as occluded
by whatever they meet, the hit's own triangle included. (Cycles tested dot(Ng, D) > 0
and dropped such directions until commit 48f7753, "Fix T95969, T91856: bake AO to vertex
color artifacts after ray offset removal", 2022, in Blender 3.1; 4.2 and 5.0 trace them.)
For smooth triangles the origin is lifted toward the smooth surface as Cycles'
`shadow_ray_offset` does (the shadow terminator geometry offset, `terminator_offset`,
default 0.1 as Blender's objects).

Guarantees:
- Occlusion rays start at p pushed off the surface along ng by OFFSET_ULPS float32 ulps of
  the hit's local scale (max of |p| and the triangle's extent around p), computed in
  float64 and rounded once: a flat surface never occludes itself, at any scale or offset.
  (With shading normals the terminator lift is added to that point.)
- `normals=None` is the geometric definition, bit for bit as before normals existed.
- Every sample is a pure function of (seed, ray index, sample index): the result is
  bit-identical for any thread count, round split or device.
- Skipped work: primary rays that miss the scene box are not traced, missed pixels get no
  occlusion rays, and (with `target_error`) converged pixels get no more samples.

Adaptive sampling, two stopping rules (issue 19), which may be combined:
- `target_error` is the image's RMSE over hit pixels against the converged AO (the
  expectation of infinitely many samples). The render estimates it as
  sqrt(mean_i efficiency(n_i) * v_i / n_i) over the hit pixels (`rmse_estimate`), v_i
  the pixel's `posterior_variance` (about its sample variance where its samples disagree;
  where they agree, not 0 but what a Beta prior fitted to the image says), and stops
  once that estimate is below RMSE_AIM * target_error. RMSE_AIM leaves room for the
  estimate's own error and for the last round's overshoot, so that the achieved RMSE lies
  in [0.7, 1.0] x target_error in at least 95% of renders (tests/kernels/render/
  test_ao_target.py over seeds; benchmarks/ao_error.py on every shared scene): that is
  the confidence the API states. Samples go where they lower the image's error most per
  ray (Neyman allocation, n_i in proportion to sigma_i): every hit pixel gets the
  minimum spp in one launch (the kernel also counts the open samples among its first
  half and quarter, so that the sampler's rate is measured before the first decision;
  a pixel's rays in one launch share the cache: two launches of half the minimum cost
  1.5x one on blade), then each round doubles the pixels below their Neyman count, those
  with the largest sigma_i^2 / n_i^2 (the variance each new ray removes; in 1/16-octave
  steps, sorted by radix) first, until the
  doubled set is predicted to remove DROP_SHORT of what is left above the aim (all of
  it when at most SHORT_NEED aim^2 a pixel is left; TAIL_MARGIN aim^2 a pixel past it,
  with at least MIN_ROUND of the rays so far, when that round would trace less than
  TAIL_ROUND of them; every pixel when it would take FULL_ROUND of the rays left, unless
  even the fastest Sobol rate could then take it below FULL_ROUND_AIM of the aim: a
  round's fixed cost is worth more than a small overshoot); sigma_i^2 is the
  Jeffreys-smoothed variance below, so that a pixel whose few samples agreed still earns
  more.
- `max_pixel_error` bounds every pixel (the rule `target_error` had before issue 19):
  pixels whose 95% half-width z * sqrt(spread * s^2 / n) is still >= it double their
  samples (`half_width`; spread as below).
A pixel's samples are always a power-of-two prefix of its Sobol sequence (when the
minimum is one), up to `max_spp`. In the half-width and the allocation s^2 is the
sample variance, and where all n samples agreed p(1-p) at the Jeffreys posterior mean
p = (k + 1/2) / (n + 1) instead of 0, so a pixel is not declared exact on the strength
of a few samples that missed a small occluder. Owen-scrambled Sobol samples have less
variance than independent ones. `spread` is measured at every sample count n a round
reaches, on the pixels whose samples disagree, from each pixel's estimate after n/2
against after n samples (`sampler_efficiency`; independent samples: ~1). For Sobol the
halves are anti-correlated, so the spread overstates the variance where it falls faster
than 1/n: `efficiency` corrects it by the rate measured on the same pixels (see
`_Counts.efficiency_at`). A count without a measurement takes the nearest smaller one's
(efficiency falls as n grows, so this is never optimistic).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import warp as wp

from ..bvh.api import Bvh
from ..bvh.node import BvhArrays
from ..bvh.traversal import closest_hit, traverse
from ..core.compile_options import MODULE_OPTIONS
from ..core.launch import (
    PARTS_PER_THREAD,
    host_threads,
    launch_split,
    load_modules,
    part_launcher,
    run_parts,
)
from ..core.mesh import DeviceMesh, Shading, triangle_corners
from ..core.ray import make_ray
from ..core.validate import as_rays, ray_range
from ..dacrt.api import dacrt_trace_mesh, dacrt_warp_modules
from ..scene.api import Placement, Scene
from ..scene.top import WARP_MODULES as SCENE_MODULES
from ..scene.top import (
    InstanceHit,
    SceneArrays,
    SceneShading,
    mesh_indices,
    mesh_vertices,
    traverse_scene,
    world_normal,
    world_point,
)
from .denoise import denoise_ao, require_denoiser
from .sampling import SAMPLERS, cosine_direction, pixel_key

wp.set_module_options(MODULE_OPTIONS)

DISTANCE_FRACTION = 0.1  # distance=None: this fraction of the scene box's diagonal
OFFSET_ULPS = 128.0  # occlusion-ray origin offset, in float32 ulps of the local scale
DEFAULT_TERMINATOR_OFFSET = 0.1  # Blender's Object.shadow_terminator_geometry_offset default
Z95 = 1.959963984540054  # two-sided 95% normal quantile
MIN_ADAPTIVE_SPP = 8  # fewest samples before a pixel's variance is trusted (measured: 4-16)
RMSE_AIM = 0.82  # target_error: stop at this fraction of it (the estimate's margin)
# Owen-scrambled Sobol on an integrand with discontinuities (an occluder's edge) in 2D:
# variance O(n^(-1 - 1/d)) = n^-1.5 (He and Wang 2015), so doubling keeps >= 2^-1.5 of it
RHO_MIN = 2.0**-1.5
DROP_SHORT = 0.8  # target_error: a round aims at this fraction of the MSE still to go,
SHORT_NEED = 1.0  # when that is over this many aim^2 (per pixel); else at all of it
FULL_ROUND = 0.5  # target_error: a round with this fraction of the rays left doubles all,
FULL_ROUND_AIM = 0.9  # if that is predicted to stay above this fraction of the aim
TAIL_ROUND = 0.125  # target_error: a round under this fraction of the rays so far aims at all
TAIL_MARGIN = 0.05  # target_error: a tail round aims this many aim^2 below the aim
MIN_ROUND = 1.0 / 32.0  # target_error: fewest rays in a round, as a fraction of those so far
DEFAULT_MAX_SPP = 1024
EFFICIENCY_MIN = 0.05  # never trust a sampler to beat independent samples by more than 20x
EFFICIENCY_PIXELS = 64  # disagreeing pixels needed to measure the efficiency in a round
ROUND_RAYS = 1 << 21  # occlusion rays per round (between progress calls) in fixed mode
PART_RAYS = 4096  # fewest occlusion rays worth a host thread of their own
LAUNCH_RAYS = 1 << 30  # most rays per launch (a launch's thread index is int32)
ENGINES = ("bvh", "dacrt")

Progress = Callable[[float, str], None]


@dataclass
class AoResult:
    ao: np.ndarray  # (R,) float32 in [0, 1]
    spp_used: np.ndarray  # (R,) int32 occlusion samples per ray (0 where the ray missed)
    # compile (Warp's, not in total), setup, primary, occlusion, total
    timings_ms: dict[str, float] = field(default_factory=dict)
    rays: dict[str, int] = field(default_factory=dict)  # primary (traced), occlusion, rounds
    # Estimated RMSE over hit pixels against the converged AO (see the module docstring);
    # None when no ray hit. Always the raw render's, also when `denoised`.
    rmse_estimate: float | None = None
    # (R, 3) float32 unit shading normal of each primary hit (0 where the ray missed)
    normals: np.ndarray | None = None
    denoised: bool = False  # `ao` is OIDN's output (render_ao(denoise=True))
    raw_ao: np.ndarray | None = None  # (R,) the render before denoising, when denoised

    def stats(self) -> dict[str, float | int | None]:
        """What the render achieved: estimated RMSE (of the raw render), mean and largest
        spp over hit pixels, rays traced (primary and occlusion), whether it was denoised."""
        hit = self.spp_used[self.spp_used > 0]
        return {
            "rmse_estimate": self.rmse_estimate,
            "spp_mean": float(hit.mean()) if len(hit) else 0.0,
            "spp_max": int(hit.max()) if len(hit) else 0,
            "rays": int(self.rays.get("primary", 0) + self.rays.get("occlusion", 0)),
            "denoised": self.denoised,
        }


@wp.struct
class Surface:
    """What occlusion rays need of one primary hit."""

    point: wp.vec3  # the hit pushed off along ng by the spawn offset (spawn_point)
    ng: wp.vec3  # unit geometric normal, facing the primary ray's origin
    n: wp.vec3  # unit shading normal (ng where flat or without normals), turned with ng
    lift: wp.vec3  # Cycles' smooth-surface offset at full strength (0 where flat)
    cutoff: float  # the triangle's shadow terminator geometry offset (0: never lifted)


@dataclass
class PrimaryHits:
    """The hit pixels of a batch of primary rays, ready to spawn occlusion rays."""

    pixels: np.ndarray  # (H,) int32 index of each hit ray in the caller's arrays
    surfaces: wp.array  # (H,) Surface of each hit
    traced: int  # primary rays traced (those that entered the scene box)


@wp.func
def spawn_point(v0: wp.vec3, v1: wp.vec3, v2: wp.vec3, u: float, v: float, n: wp.vec3d) -> wp.vec3:
    # Robust spawn point (Ray Tracing Gems ch. 6, Waechter and Binder; PBR 4th ed. 6.8.6):
    # p from barycentrics in float64 lies on the triangle's plane; it is pushed along n by
    # OFFSET_ULPS float32 ulps of its local scale, which bounds both the float32 rounding
    # of the result and the watertight test's error in t for triangles this size.
    a = wp.vec3d(v0)
    b = wp.vec3d(v1)
    c = wp.vec3d(v2)
    bu = wp.float64(u)
    bv = wp.float64(v)
    p = a + (b - a) * bu + (c - a) * bv
    scale = wp.max(wp.max(wp.abs(p[0]), wp.abs(p[1])), wp.abs(p[2]))
    for k in range(3):
        reach = wp.max(wp.max(wp.abs(a[k] - p[k]), wp.abs(b[k] - p[k])), wp.abs(c[k] - p[k]))
        scale = wp.max(scale, reach)
    offset = scale * wp.float64(OFFSET_ULPS * 5.9604645e-08)
    return wp.vec3(p + n * offset)


@wp.func
def shading_normal(n0: wp.vec3, n1: wp.vec3, n2: wp.vec3, u: float, v: float, ng: wp.vec3,
                   backfacing: bool) -> wp.vec3:
    # Cycles' triangle_smooth_normal (kernel/geom/triangle.h): the corner normals weighted
    # by the hit's barycentrics, normalised; ng where that is zero (a flat triangle's zero
    # corners). shader_setup_from_ray flips it with ng on a back face, so that it lies on
    # the viewer's side of the surface whenever the mesh's normals agree with its winding.
    n = n0 * (1.0 - u - v) + n1 * u + n2 * v
    out = ng
    if wp.length_sq(n) > 0.0:
        out = wp.normalize(n)
        if backfacing:
            out = -out
    return out


@wp.func
def smooth_surface_offset(p0: wp.vec3, p1: wp.vec3, p2: wp.vec3, n0: wp.vec3, n1: wp.vec3,
                          n2: wp.vec3, u: float, v: float, ng: wp.vec3) -> wp.vec3:
    # Cycles' shadow_ray_smooth_surface_offset (kernel/light/sample.h; Hanika 2021,
    # "Hacking the shadow terminator", Ray Tracing Gems II ch. 4): how far the smooth
    # surface that the corner normals describe lies above the flat triangle at the hit, as
    # a vector along the interpolated normal. Cycles' names: wu, wv, ww weight the corners.
    wu = 1.0 - u - v
    wv = u
    ww = v
    p = p0 * wu + p1 * wv + p2 * ww
    n = n0 * wu + n1 * wv + n2 * ww  # not normalised, as in Cycles
    # Parabolic approximation
    a = wp.dot(n2 - n0, p0 - p2)
    b = wp.dot(n2 - n1, p1 - p2)
    c = wp.dot(n1 - n0, p1 - p0)
    h = a * wu * (wu - 1.0) + (a + b + c) * wu * wv + b * wv * (wv - 1.0)
    if wp.dot(n, ng) > 0.0:
        # Local linear envelope
        h0 = wp.max(wp.max(wp.dot(p1 - p0, n0), wp.dot(p2 - p0, n0)), 0.0)
        h1 = wp.max(wp.max(wp.dot(p0 - p1, n1), wp.dot(p2 - p1, n1)), 0.0)
        h2 = wp.max(wp.max(wp.dot(p0 - p2, n2), wp.dot(p1 - p2, n2)), 0.0)
        h0 = wp.max(wp.dot(p0 - p, n0) + h0, 0.0)
        h1 = wp.max(wp.dot(p1 - p, n1) + h1, 0.0)
        h2 = wp.max(wp.dot(p2 - p, n2) + h2, 0.0)
        h = wp.max(wp.min(wp.min(h0, h1), h2), h * 0.5)
    else:  # seen from behind the normals: the same envelope below
        h0 = wp.max(wp.max(wp.dot(p0 - p1, n0), wp.dot(p0 - p2, n0)), 0.0)
        h1 = wp.max(wp.max(wp.dot(p1 - p0, n1), wp.dot(p1 - p2, n1)), 0.0)
        h2 = wp.max(wp.max(wp.dot(p2 - p0, n2), wp.dot(p2 - p1, n2)), 0.0)
        h0 = wp.max(wp.dot(p - p0, n0) + h0, 0.0)
        h1 = wp.max(wp.dot(p - p1, n1) + h1, 0.0)
        h2 = wp.max(wp.dot(p - p2, n2) + h2, 0.0)
        h = wp.min(-wp.min(wp.min(h0, h1), h2), h * 0.5)
    return n * h


@wp.func
def terminator_amount(n: wp.vec3, ng: wp.vec3, w: wp.vec3, cutoff: float) -> float:
    # Cycles' shadow_ray_offset (kernel/light/sample.h): only rays close to the terminator
    # (w near ng's horizon, or near n's) are lifted, fully below a dot of `cutoff` and
    # fading out to 0 above it. AO's directions lie above n (cosine samples about it), so
    # Cycles' transmission case (dot(n, w) < 0) never arises here.
    nl = wp.dot(n, w)
    ngl = wp.dot(ng, w)
    amount = float(0.0)
    if cutoff > 0.0:
        if nl < cutoff:
            amount = wp.clamp(2.0 - (ngl + nl) / cutoff, 0.0, 1.0)
        else:
            amount = wp.clamp(1.0 - ngl / cutoff, 0.0, 1.0)
    return amount


@wp.func
def occlusion_origin(s: Surface, w: wp.vec3) -> wp.vec3:
    """Where the occlusion ray in direction w starts: the spawn point, lifted toward the
    smooth surface by Cycles' terminator amount (unchanged where that is 0)."""
    o = s.point
    amount = terminator_amount(s.n, s.ng, w, s.cutoff)
    if amount > 0.0:
        o = s.point + s.lift * amount
    return o


@wp.func
def surface_at(v0: wp.vec3, v1: wp.vec3, v2: wp.vec3, d: wp.vec3, u: float, v: float,
               smooth: bool, n0: wp.vec3, n1: wp.vec3, n2: wp.vec3, cutoff: float,
               mirrored: bool) -> Surface:
    """The spawn point, normals and terminator lift of a hit at (u, v) on the triangle
    (v0, v1, v2) (world space), with corner normals n0..n2 where `smooth` (see `Surface`).
    `mirrored`: the corners are a mirrored instance's, whose world winding is reversed."""
    # Geometric normal in float64 (degenerate triangles are never hit, so it is non-zero).
    # A mirror reverses the winding against the (inverse-transpose) corner normals: the
    # front face is the other side, as for a flattened mirrored mesh (addon/export.py
    # reverses its corners).
    n = wp.normalize(wp.cross(wp.vec3d(v1) - wp.vec3d(v0), wp.vec3d(v2) - wp.vec3d(v0)))
    if mirrored:
        n = -n
    backfacing = wp.dot(n, wp.vec3d(d)) > wp.float64(0.0)
    if backfacing:
        n = -n
    s = Surface()
    s.point = spawn_point(v0, v1, v2, u, v, n)
    s.ng = wp.vec3(n)
    s.n = s.ng
    s.lift = wp.vec3(0.0)
    s.cutoff = 0.0
    if smooth:
        s.n = shading_normal(n0, n1, n2, u, v, s.ng, backfacing)
        s.lift = smooth_surface_offset(v0, v1, v2, n0, n1, n2, u, v, s.ng)
        s.cutoff = cutoff
    return s


@wp.func
def surface(vertices: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.vec3i),
            shading: Shading, d: wp.vec3, triangle: int, u: float, v: float) -> Surface:
    """`surface_at` of a hit on a mesh's triangle."""
    t = triangle_corners(vertices, indices, triangle)
    n0 = wp.vec3(0.0)
    n1 = wp.vec3(0.0)
    n2 = wp.vec3(0.0)
    cutoff = float(0.0)
    if shading.smooth != 0:
        n0 = shading.normals[3 * triangle]
        n1 = shading.normals[3 * triangle + 1]
        n2 = shading.normals[3 * triangle + 2]
        cutoff = shading.offsets[triangle]
    return surface_at(t[0], t[1], t[2], d, u, v, shading.smooth != 0, n0, n1, n2, cutoff,
                      False)


@wp.func
def instance_surface(scene: SceneArrays, shading: SceneShading, d: wp.vec3,
                     ih: InstanceHit) -> Surface:
    """`surface_at` of a hit in an instance: its triangle and corner normals taken to world
    space (points by M, rounded once as a flattened scene's vertices would be; normals by
    the inverse transpose); a mirrored instance's front face is the side its normals
    face, as when it is flattened with its corners reversed. The Surface is the world-space
    one."""
    rec = scene.instances[ih.instance]
    mesh = scene.meshes[rec.mesh]
    tri = ih.hit.triangle
    t = triangle_corners(mesh_vertices(mesh), mesh_indices(mesh), tri)
    base = int(-1)
    if shading.smooth != 0:
        base = shading.base[rec.mesh]
    n0 = wp.vec3(0.0)
    n1 = wp.vec3(0.0)
    n2 = wp.vec3(0.0)
    if base >= 0:
        n0 = world_normal(rec, shading.normals[base + 3 * tri])
        n1 = world_normal(rec, shading.normals[base + 3 * tri + 1])
        n2 = world_normal(rec, shading.normals[base + 3 * tri + 2])
    return surface_at(world_point(rec, t[0]), world_point(rec, t[1]), world_point(rec, t[2]),
                      d, ih.hit.u, ih.hit.v, base >= 0, n0, n1, n2,
                      shading.offsets[ih.instance], wp.determinant(rec.lin) < wp.float64(0.0))


@wp.struct
class MeshTracer:
    """A single mesh's BVH and triangles: what the render kernels trace and shade."""

    bvh: BvhArrays
    vertices: wp.array(dtype=wp.vec3)
    indices: wp.array(dtype=wp.vec3i)


@wp.func
def closest_surface(g: MeshTracer, shading: Shading, o: wp.vec3, d: wp.vec3, tmin: float,
                    tmax: float):
    """(Surface, True) of the closest hit in [tmin, tmax], or (anything, False)."""
    h = closest_hit(g.bvh, o, d, tmin, tmax)
    if h.triangle >= 0:
        return surface(g.vertices, g.indices, shading, d, h.triangle, h.u, h.v), True
    return Surface(), False


@wp.func  # a Warp overload of the one above (by the first argument's type)
def closest_surface(g: SceneArrays, shading: SceneShading, o: wp.vec3, d: wp.vec3,  # noqa: F811
                    tmin: float, tmax: float):
    """`closest_surface` through a two-level scene."""
    ih = traverse_scene(g, o, d, tmin, tmax, False)
    if ih.instance >= 0:
        return instance_surface(g, shading, d, ih), True
    return Surface(), False


@wp.func
def occluded(g: BvhArrays, o: wp.vec3, w: wp.vec3, distance: float, find_any: bool) -> bool:
    """Whether a triangle lies within `distance` along w from o."""
    return traverse(g, make_ray(o, w), 0.0, distance, find_any).triangle >= 0


@wp.func  # a Warp overload of the one above
def occluded(g: SceneArrays, o: wp.vec3, w: wp.vec3, distance: float,  # noqa: F811
             find_any: bool) -> bool:
    """`occluded` in a two-level scene."""
    return traverse_scene(g, o, w, 0.0, distance, find_any).instance >= 0


@wp.kernel
def primary_kernel(
    tracer: Any,  # MeshTracer or SceneArrays
    shading: Any,  # Shading or SceneShading
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    tmin: wp.array(dtype=float),
    tmax: wp.array(dtype=float),
    out_surface: wp.array(dtype=Surface),
    out_hit: wp.array(dtype=int),
):
    i = wp.tid()
    s, hit = closest_surface(tracer, shading, origins[i], directions[i], tmin[i], tmax[i])
    out_hit[i] = 0
    if hit:
        out_surface[i] = s
        out_hit[i] = 1


@wp.kernel
def surface_kernel(
    vertices: wp.array(dtype=wp.vec3),
    indices: wp.array(dtype=wp.vec3i),
    shading: Shading,
    directions: wp.array(dtype=wp.vec3),
    triangle: wp.array(dtype=int),
    u: wp.array(dtype=float),
    v: wp.array(dtype=float),
    out_surface: wp.array(dtype=Surface),
):
    """Surfaces of hits found by another tracer (engine="dacrt")."""
    i = wp.tid()
    out_surface[i] = surface(vertices, indices, shading, directions[i], triangle[i], u[i], v[i])


@wp.kernel
def occlusion_kernel(
    bvh: Any,  # BvhArrays or SceneArrays
    surfaces: wp.array(dtype=Surface),
    pixels: wp.array(dtype=int),
    active: wp.array(dtype=int),  # hit-pixel index of each slot of this round
    slot0: int,  # the first slot of this launch
    first: int,  # the first sample index of this round (the same for every slot)
    count: int,  # samples per slot this round
    sampler: int,
    seed: int,
    distance: float,
    find_any: int,  # always 1; see below
    mid: int,  # out_open_mid counts the open samples with index below this (absolute)
    quarter: int,  # out_open_quarter: those below this
    out_open: wp.array(dtype=int),  # per slot: open samples (accumulated)
    out_open_mid: wp.array(dtype=int),
    out_open_quarter: wp.array(dtype=int),
):
    # One occlusion ray per thread, slot-major, so the rays (not the pixels) are split
    # between host threads. A slot's rays never straddle two launches: the plain
    # read-modify-write adds below need no atomics (Warp's are not atomic on CPU).
    # Cosine-weighted estimator (PBR 4th ed. 13.6.3 / A.5.3): each sample is V(p, w).
    t = wp.tid()
    s = t % count
    j = slot0 + t // count
    k = active[j]
    hit = surfaces[k]
    w = cosine_direction(hit.n, sampler, pixel_key(pixels[k], seed), first + s)
    # traverse() with a run-time any-hit flag, as trace_kernel calls it: measured 25-30%
    # faster on CPU than bvh_trace.any_hit, whose flag is the literal True.
    if not occluded(bvh, occlusion_origin(hit, w), w, distance, find_any != 0):
        out_open[j] += 1
        if first + s < mid:
            out_open_mid[j] += 1
            if first + s < quarter:
                out_open_quarter[j] += 1


@wp.kernel
def rays_kernel(
    surfaces: wp.array(dtype=Surface),
    pixels: wp.array(dtype=int),
    first: int,
    count: int,
    sampler: int,
    seed: int,
    out_origin: wp.array(dtype=wp.vec3),
    out_dir: wp.array(dtype=wp.vec3),
):
    i, s = wp.tid()
    key = pixel_key(pixels[i], seed)
    hit = surfaces[i]
    w = cosine_direction(hit.n, sampler, key, first + s)
    out_origin[i * count + s] = occlusion_origin(hit, w)
    out_dir[i * count + s] = w


for _tracer, _shading in ((MeshTracer, Shading), (SceneArrays, SceneShading)):
    wp.overload(primary_kernel, {"tracer": _tracer, "shading": _shading})
wp.overload(occlusion_kernel, {"bvh": BvhArrays})
wp.overload(occlusion_kernel, {"bvh": SceneArrays})


# --- host side ---------------------------------------------------------------------------


def default_distance(bvh: Bvh | Scene | Placement) -> float:
    """distance=None: DISTANCE_FRACTION of the scene box's diagonal (1.0 for an empty scene);
    of a Placement too, the same box before any BVH (backend/frames.py's culling)."""
    diag = float(np.linalg.norm(bvh.bounds[1].astype(np.float64) - bvh.bounds[0]))
    return DISTANCE_FRACTION * diag if math.isfinite(diag) and diag > 0.0 else 1.0


@wp.kernel
def box_candidates_kernel(lo: wp.vec3d, hi: wp.vec3d, origins: wp.array(dtype=wp.vec3),
                          directions: wp.array(dtype=wp.vec3), tmin: wp.array(dtype=float),
                          tmax: wp.array(dtype=float), touches: wp.array(dtype=int)):
    # A float64 slab test: exact enough that the box's widening covers its rounding.
    i = wp.tid()
    o = origins[i]
    d = directions[i]
    enter = wp.float64(tmin[i])
    leave = wp.float64(tmax[i])
    inside = int(1)
    for k in range(3):
        ok = wp.float64(o[k])
        if d[k] == 0.0:  # parallel to the slab: inside it or never
            if ok < lo[k] or ok > hi[k]:
                inside = 0
        else:
            inv = wp.float64(1.0) / wp.float64(d[k])
            a = (lo[k] - ok) * inv
            b = (hi[k] - ok) * inv
            enter = wp.max(enter, wp.min(a, b))
            leave = wp.min(leave, wp.max(a, b))
    touches[i] = 0
    if inside == 1 and enter <= leave:
        touches[i] = 1


def box_candidates(bounds: np.ndarray, origins: wp.array, directions: wp.array,
                   tmin: wp.array, tmax: wp.array, threads: int) -> np.ndarray:
    """Indices of rays whose [tmin, tmax] segment may touch the box (conservative: the box
    is widened by 1e-5 of its size so float error never drops a ray that hits). On the
    device: in numpy, with its float64 temporaries, this cost more than tracing the rays
    (1024x768 camera rays: 290 ms against a 30-150 ms primary trace)."""
    lo = bounds[0].astype(np.float64)
    hi = bounds[1].astype(np.float64)
    if not np.all(np.isfinite(lo)):
        return np.zeros(0, dtype=np.int32)
    pad = 1e-5 * (np.abs(hi - lo).max() + np.abs(lo).max() + np.abs(hi).max()) + 1e-30
    touches = wp.empty(origins.shape[0], dtype=int, device=origins.device)
    launch_split(box_candidates_kernel, origins.shape[0],
                 [wp.vec3d(*(lo - pad)), wp.vec3d(*(hi + pad))],
                 [origins, directions, tmin, tmax], [], [touches], origins.device, threads)
    return np.flatnonzero(touches.numpy()).astype(np.int32)


def scene_mesh(bvh: Bvh) -> DeviceMesh:
    """The BVH's mesh on the device (made here for a `Bvh` put together by hand)."""
    if bvh.mesh is None:
        bvh.mesh = DeviceMesh(bvh.vertices, bvh.indices, bvh.device)
    return bvh.mesh


def scene_shading(bvh: Bvh | Scene, normals, terminator_offset) -> Shading | SceneShading:
    """The device shading inputs of a mesh (`DeviceMesh.shading`) or a scene
    (`Scene.shading`: normals per mesh, offsets per instance), validated and kept."""
    if isinstance(bvh, Scene):
        return bvh.shading(normals, terminator_offset)
    return scene_mesh(bvh).shading(normals, terminator_offset)


def check_tracer(bvh, engine: str) -> None:
    """What render_ao traces through: a Bvh with either engine, a Scene with engine="bvh"."""
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {list(ENGINES)}, got {engine!r}")
    if isinstance(bvh, Scene):
        if engine == "dacrt":
            raise ValueError('engine="dacrt" traces one world-space triangle list; a two-level '
                             'Scene is traced with engine="bvh" (or flatten it into one mesh)')
    elif not isinstance(bvh, Bvh):
        raise ValueError(f"render_ao takes a Bvh (build_bvh) or a Scene (build_scene), got "
                         f"{type(bvh).__name__}")


def trace_primary(bvh: Bvh | Scene, origins: np.ndarray, directions: np.ndarray, tmin=0.0,
                  tmax=np.inf, threads: int | None = None, engine: str = "bvh",
                  normals=None,
                  terminator_offset: float | np.ndarray = DEFAULT_TERMINATOR_OFFSET,
                  ) -> PrimaryHits:
    """Closest hits of the primary rays that enter the scene box, as `Surface`s for
    occlusion rays (`normals`, `terminator_offset`: see `render_ao`)."""
    tmin_a, tmax_a = ray_range(tmin, tmax, len(origins))
    device = bvh.device
    nthreads = host_threads(device, threads)
    host = ((origins, wp.vec3), (directions, wp.vec3), (tmin_a, float), (tmax_a, float))
    rays = [wp.array(x, dtype=dt, device=device) for x, dt in host]
    cand = box_candidates(bvh.bounds, *rays, nthreads)
    m = len(cand)
    shading = scene_shading(bvh, normals, terminator_offset)
    if engine == "dacrt":
        mesh = scene_mesh(bvh)
        h = dacrt_trace_mesh(mesh, origins[cand], directions[cand], tmin_a[cand], tmax_a[cand])
        keep = np.flatnonzero(h.triangle >= 0)
        n = len(keep)
        surfaces = wp.empty(n, dtype=Surface, device=device)
        if n:
            wp.launch(surface_kernel, dim=n, inputs=[
                mesh.v, mesh.f, shading, wp.array(directions[cand][keep], dtype=wp.vec3,
                                                  device=device),
                *(wp.array(x[keep], device=device) for x in (h.triangle, h.u, h.v)),
            ], outputs=[surfaces], device=device)
        return PrimaryHits(pixels=cand[keep], surfaces=surfaces, traced=m)
    if isinstance(bvh, Scene):
        tracer = bvh.arrays
    else:
        mesh = scene_mesh(bvh)
        tracer = MeshTracer()
        tracer.bvh = bvh.arrays
        tracer.vertices, tracer.indices = mesh.v, mesh.f  # on the device since the build
    surfaces = wp.empty(m, dtype=Surface, device=device)
    hit = wp.empty(m, dtype=int, device=device)
    if m:
        per_item = rays if m == len(origins) else [
            wp.array(x[cand], dtype=dt, device=device) for x, dt in host]
        launch_split(primary_kernel, m, [tracer, shading], per_item, [],
                     [surfaces, hit], device, nthreads)
    keep = np.flatnonzero(hit.numpy())
    sel = wp.array(keep.astype(np.int32), dtype=int, device=device)
    kept = wp.empty(len(keep), dtype=Surface, device=device)
    if len(keep):
        wp.launch(_gather_surfaces, dim=len(keep), inputs=[surfaces, sel, kept], device=device)
    return PrimaryHits(pixels=cand[keep], surfaces=kept, traced=m)


@wp.kernel
def _gather_surfaces(src: wp.array(dtype=Surface), sel: wp.array(dtype=int),
                     dst: wp.array(dtype=Surface)):
    i = wp.tid()
    dst[i] = src[sel[i]]


def occlusion_rays(hits: PrimaryHits, first: int, count: int, seed: int = 0,
                   sampler: str = "sobol", select: np.ndarray | None = None,
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The origins and unit directions of samples first..first+count-1 of every hit pixel
    (or of the hit pixels `select` indexes), each (H*count, 3) float32, pixel-major:
    exactly the rays `render_ao` traces (for DACRT and for peers in benchmarks/tests)."""
    return _occlusion_rays(hits, first, count, int(seed), _sampler(sampler), select)


def _occlusion_rays(hits, first, count, seed, sampler_id, select) -> tuple[np.ndarray, ...]:
    device = hits.surfaces.device
    surfaces, pixels = hits.surfaces, hits.pixels
    if select is not None:
        sel = wp.array(np.asarray(select, np.int32), dtype=int, device=device)
        surfaces = wp.empty(len(select), dtype=Surface, device=device)
        if len(select):
            wp.launch(_gather_surfaces, dim=len(select), inputs=[hits.surfaces, sel, surfaces],
                      device=device)
        pixels = pixels[select]
    h = len(pixels)
    origins = wp.empty(h * count, dtype=wp.vec3, device=device)
    dirs = wp.empty(h * count, dtype=wp.vec3, device=device)
    if h and count:
        pix = wp.array(pixels, dtype=int, device=device)
        wp.launch(rays_kernel, dim=(h, count),
                  inputs=[surfaces, pix, int(first), int(count), sampler_id, seed],
                  outputs=[origins, dirs], device=device)
    return origins.numpy().reshape(-1, 3), dirs.numpy().reshape(-1, 3)


def _sampler(sampler: str) -> int:
    if sampler not in SAMPLERS:
        raise ValueError(f"sampler must be one of {sorted(SAMPLERS)}, got {sampler!r}")
    return SAMPLERS[sampler]


def _check_args(spp, distance, seed, targets, min_spp_max) -> None:
    if isinstance(spp, bool) or not isinstance(spp, int | np.integer) or spp < 1:
        raise ValueError(f"spp must be an integer >= 1, got {spp!r}")
    if distance is not None and not (float(distance) > 0.0):
        raise ValueError(f"distance must be > 0 (or None for the scene default), got {distance!r}")
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer):
        raise ValueError(f"seed must be an integer, got {seed!r}")
    for name, value in targets.items():
        if value is not None and not (0.0 < float(value) < 1.0):
            raise ValueError(f"{name} must be in (0, 1) or None, got {value!r}")
    if any(v is not None for v in targets.values()) and min_spp_max[1] < min_spp_max[0]:
        raise ValueError(
            f"max_spp ({min_spp_max[1]}) must be >= the minimum spp ({min_spp_max[0]}): "
            "raise max_spp or lower spp"
        )


def render_ao(
    bvh: Bvh | Scene,
    origins: np.ndarray,
    directions: np.ndarray,
    spp: int = 16,
    distance: float | None = None,
    seed: int = 0,
    target_error: float | None = None,
    *,
    max_pixel_error: float | None = None,
    tmin: float | np.ndarray = 0.0,
    tmax: float | np.ndarray = np.inf,
    threads: int | None = None,
    max_spp: int = DEFAULT_MAX_SPP,
    sampler: str = "sobol",
    engine: str = "bvh",
    normals: np.ndarray | None = None,
    terminator_offset: float | np.ndarray = DEFAULT_TERMINATOR_OFFSET,
    progress: Progress | None = None,
    denoise: bool = False,
    image_shape: tuple[int, int] | None = None,
) -> AoResult:
    """AO per primary ray (see the module docstring for the definition and guarantees).

    Fixed mode (neither target): `spp` samples per hit pixel. Adaptive mode: each hit pixel
    gets at least max(spp, MIN_ADAPTIVE_SPP) samples, then samples are doubled in rounds,
    up to `max_spp` per pixel, until the image's estimated RMSE over hit pixels is below
    RMSE_AIM * `target_error` (the achieved RMSE is then within [0.7, 1.0] x target_error
    with >= 95% confidence) and every pixel's 95% half-width (`half_width`) is below
    `max_pixel_error` (each rule only when given). `result.rmse_estimate` is the estimate
    in every mode. `distance=None` is DISTANCE_FRACTION of the scene
    box diagonal. `sampler`: "sobol" (Owen-scrambled, default) or "random"; both unbiased.
    `engine`: "bvh" traces through `bvh`; "dacrt" traces the same rays (primary, then each
    round's occlusion rays) with the task-pool DACRT, without using the BVH: the same result
    to float32 rounding.
    `normals`: None (geometric normals, flat shading) or (T, 3, 3) shading normals, one per
    corner of each of the BVH's triangles in index order (Blender's `Mesh.corner_normals`
    of the loop triangles; need not be unit; three zero corners mark a flat triangle).
    `terminator_offset`: Cycles' shadow terminator geometry offset, one number or (T,) per
    triangle in [0, 1] (Blender's per-object setting, default 0.1); only smooth triangles
    use it. Both arrays are read once per set of objects and taken as read-only.
    With a two-level `Scene` (kernels.scene.build_scene) instead of a Bvh: `normals` is None
    or one entry per mesh (None, or that mesh's (T_k, 3, 3) in object space; they are taken
    to world space by each instance's inverse transpose), `terminator_offset` one number or
    (I,) per instance, and engine="bvh" only; the rays and the AO are in world space.
    `progress(fraction, phase)` is called between rounds; an exception it raises cancels
    the render.
    `denoise=True` (needs the `scenesort[denoise]` extra, checked before tracing) runs
    OIDN on the image (`denoise.denoise_ao`): the rays must be a row-major `image_shape` =
    (height, width) image. `ao` is then the denoised image, `raw_ao` the render's own;
    `rmse_estimate` stays the raw render's (nothing measures the denoised error here).
    """
    check_tracer(bvh, engine)
    modules = WARP_MODULES + SCENE_MODULES + (dacrt_warp_modules("pool") if engine == "dacrt"
                                              else ())
    compile_ms = load_modules(bvh.device, *modules)  # compiling is not rendering
    t_start = time.perf_counter()
    adaptive = target_error is not None or max_pixel_error is not None
    min_spp = max(int(spp), MIN_ADAPTIVE_SPP) if adaptive else int(spp)
    _check_args(spp, distance, seed,
                {"target_error": target_error, "max_pixel_error": max_pixel_error},
                (min_spp, int(max_spp)))
    if denoise:
        require_denoiser()
        if image_shape is None or int(np.prod(image_shape)) != len(origins):
            raise ValueError(f"denoise=True needs image_shape=(height, width) with height * "
                             f"width = the number of rays ({len(origins)}), got {image_shape!r}")
    sampler_id = _sampler(sampler)
    origins, directions = as_rays(origins, directions)
    scene_shading(bvh, normals, terminator_offset)  # checked (and kept) before tracing
    r = len(origins)
    dist = default_distance(bvh) if distance is None else float(distance)
    device = bvh.device
    nthreads = host_threads(device, threads)
    last = [0.0]

    def report(fraction: float, phase: str) -> None:
        last[0] = max(last[0], fraction)  # adaptive estimates may dip; the bar never does
        if progress is not None:
            progress(last[0], phase)

    timings: dict[str, float] = {"compile": compile_ms,
                                 "setup": (time.perf_counter() - t_start) * 1e3}

    report(0.0, "primary")
    t0 = time.perf_counter()
    hits = trace_primary(bvh, origins, directions, tmin, tmax, threads, engine, normals,
                         terminator_offset)
    wp.synchronize_device(device)
    timings["primary"] = (time.perf_counter() - t0) * 1e3

    t0 = time.perf_counter()
    h = len(hits.pixels)
    counts = _Counts(*(np.zeros(h, dtype=np.int64) for _ in range(3)))
    pix = wp.array(hits.pixels, dtype=int, device=device)
    trace_round = _occlusion_round if engine == "bvh" else _occlusion_round_dacrt
    rounds = 0

    def trace(select: np.ndarray, count: int) -> None:
        """Samples n..n+count-1 of the `select`ed pixels, which all have n samples."""
        first = int(counts.done[select[0]])
        end = first + count
        # the nested estimates, after about end / 2 and end / 4 samples: counted in the
        # launch where they reach into it, else those kept from the rounds before
        mid, quarter = max(end // 2, first), end // 4 if end % 4 == 0 else -1
        opened, opened_mid, opened_quarter = trace_round(
            bvh, hits, pix, select, first, count, sampler_id, int(seed), dist, nthreads,
            mid, quarter)
        open_now = counts.open[select]
        open_mid = open_now + opened_mid
        open_quarter = (open_now + opened_quarter if quarter >= first
                        else counts.before[select] if 2 * quarter == first == count else None)
        counts.measure(end, mid, open_mid, open_now + opened, open_quarter)
        counts.before[select] = open_mid
        counts.open[select] = open_now + opened
        counts.done[select] += count
        counts.changed()

    if not adaptive:
        count = max(1, min(min_spp, ROUND_RAYS // max(h, 1)))
        everyone = np.arange(h)
        while h and count > 0:
            report(float(counts.done.sum()) / (min_spp * h), "occlusion")
            trace(everyone, count)
            rounds += 1
            count = min(count, min_spp - int(counts.done[0]))
    else:
        select = np.arange(h)
        aim = None if target_error is None else RMSE_AIM * float(target_error)
        mse0 = None
        while h and len(select):
            if aim is not None and mse0 is not None:
                report(_progress(mse0, counts.mse(), aim), "occlusion")
            else:
                report(_fraction(counts.done, len(select), int(counts.done[select[0]])),
                       "occlusion")
            for n in np.unique(counts.done[select]):  # one launch set per sample count
                # doubling: Sobol prefixes of 2^k; the minimum's nested estimates (after a
                # quarter and a half of it) measure how fast the variance falls before
                # the first decision
                trace(select[counts.done[select] == n], int(n) or min_spp)
            rounds += 1
            mse0 = counts.mse() if mse0 is None else mse0
            select = _next_round(counts, aim, max_pixel_error, int(max_spp))
    timings["occlusion"] = (time.perf_counter() - t0) * 1e3

    ao = np.ones(r, dtype=np.float32)
    spp_used = np.zeros(r, dtype=np.int32)
    normals_out = np.zeros((r, 3), dtype=np.float32)
    if h:
        ao[hits.pixels] = (counts.open / counts.done).astype(np.float32)
        spp_used[hits.pixels] = counts.done.astype(np.int32)
        normals_out[hits.pixels] = hits.surfaces.numpy()["n"]
    raw_ao = None
    if denoise:
        t0 = time.perf_counter()
        raw_ao, ao = ao, denoise_ao(ao, normals_out, spp_used > 0, image_shape)
        timings["denoise"] = (time.perf_counter() - t0) * 1e3
    timings["total"] = (time.perf_counter() - t_start) * 1e3
    report(1.0, "done")
    return AoResult(
        ao=ao,
        spp_used=spp_used,
        timings_ms=timings,
        rays={"primary": hits.traced, "occlusion": int(counts.done.sum()), "rounds": rounds},
        rmse_estimate=math.sqrt(counts.mse()) if h else None,
        normals=normals_out,
        denoised=denoise,
        raw_ao=raw_ao,
    )


@dataclass
class _Counts:
    """Per hit pixel: samples traced and open; per sample count n reached by doubling, the
    `sampler_efficiency` of the halves (n/2 against n, `spread`) where enough pixels
    disagreed, and how fast the variance fell on those pixels (`rho`)."""

    done: np.ndarray
    open: np.ndarray
    before: np.ndarray  # open among the first half of each pixel's samples
    spread: dict[int, float] = field(default_factory=dict)
    rho: dict[int, float] = field(default_factory=dict)
    # per count: the pooled sums of every round that reached it (rounds of one count are
    # pooled, so a small late group does not overwrite what thousands of pixels measured)
    sums: dict[int, np.ndarray] = field(default_factory=dict)
    sums_before: dict[int, np.ndarray] = field(default_factory=dict)
    cached: np.ndarray | None = None  # `contribution` since the last `changed()`

    def measure(self, n: int, mid: int, open_mid: np.ndarray, open_end: np.ndarray,
                open_before: np.ndarray | None) -> None:
        """Pool one round's nested estimates (mid against n samples; before: mid/2
        against mid) at count n."""
        def pooled(store: dict, key: int, *args: np.ndarray) -> np.ndarray:
            store[key] = store.get(key, 0.0) + _spread_sums(*args)
            return store[key]

        total = pooled(self.sums, n, open_mid, mid, open_end, n)
        if total[2] < EFFICIENCY_PIXELS:
            return
        self.spread[n] = float(np.clip(total[0] / total[1], EFFICIENCY_MIN, 1.0))
        if open_before is not None:  # the same pixels' previous halves: the rate
            before = pooled(self.sums_before, n, open_before, mid // 2, open_mid, mid)
            if before[2] >= EFFICIENCY_PIXELS:
                ratio = (total[0] / total[1]) / (2.0 * before[0] / before[1])
                self.rho[n] = min(max(ratio, RHO_MIN), 0.5)

    def efficiency_at(self, n: np.ndarray) -> np.ndarray:
        """The sampler's efficiency (variance over the independent samples' p(1-p)/n) at
        each count n. The halves' spread overstates it where the variance falls faster than
        1/n (Owen-scrambled Sobol: the halves are anti-correlated): with
        rho = Var(n)/Var(n/2) it is spread * rho / (1 - rho) (spread itself when rho = 1/2,
        independent samples). rho is spread(n) / (2 spread(n/2)) on the pixels that
        doubled to n, in [RHO_MIN, 1/2]; at the first count, that of the next; 1/2 (the
        pessimistic end) when unmeasured. A count without a measurement takes the nearest
        smaller one's (efficiency falls as n grows, so this never flatters); 1.0 below
        every one."""
        return self._at(n, lambda m: self.spread[m] * self._rho(m) / (1.0 - self._rho(m)))

    def spread_at(self, n: np.ndarray) -> np.ndarray:
        """The halves' spread itself at each count (what max_pixel_error has always used:
        not corrected for rho, so a pixel bound never rests on a rate estimate)."""
        return self._at(n, lambda m: self.spread[m])

    def _at(self, n: np.ndarray, value: Callable[[int], float]) -> np.ndarray:
        known = sorted(self.spread)
        values = np.array([1.0] + [value(m) for m in known])
        return values[np.searchsorted(np.array(known, dtype=np.int64), n, side="right")]

    def _rho(self, m: int) -> float:
        return self.rho.get(m, self.rho.get(2 * m, 0.5))

    def rho_at(self, n: np.ndarray) -> np.ndarray:
        """Var(2n) / Var(n) expected for each count n: the latest measured rho at or
        below 2n (1/2 when none)."""
        known = sorted(self.rho)
        values = np.array([0.5] + [self.rho[m] for m in known])
        return values[np.searchsorted(np.array(known, dtype=np.int64), 2 * n, side="right")]

    def contribution(self) -> np.ndarray:
        """Each hit pixel's estimated squared error, efficiency * s^2 / n (kept until the
        next `changed()`: the progress report, the allocation and the result ask for it
        between two rounds, each a pass over every hit pixel)."""
        if self.cached is None:
            eff = self.efficiency_at(self.done)
            self.cached = eff * posterior_variance(self.open, self.done, eff) / self.done
        return self.cached

    def changed(self) -> None:
        """The counts changed (a round was traced): forget `contribution`."""
        self.cached = None

    def mse(self) -> float:
        """Estimated mean squared error over hit pixels, mean of `contribution`."""
        return float(np.mean(self.contribution()))


def _next_round(counts: _Counts, aim: float | None, max_pixel_error: float | None,
                max_spp: int) -> np.ndarray:
    """The hit pixels whose samples the next round doubles (empty: done).

    max_pixel_error: every pixel whose half-width is not yet below it. aim (the RMSE to
    reach): while the estimate is above it, the pixels below their Neyman count
    n*_i = sigma_i sum_j sigma_j / (H aim^2) by more than a factor sqrt(2), those with the
    most variance removed per ray first, as many as the estimate predicts it needs (then,
    if those are not enough, the others in the same order)."""
    n, k = counts.done, counts.open
    eff = counts.efficiency_at(n)
    room = n < max_spp
    want = np.zeros(len(n), dtype=bool)
    if max_pixel_error is not None:
        want |= room & (half_width(k, n, counts.spread_at(n)) >= max_pixel_error)
    if aim is not None:
        contribution = counts.contribution()
        # doubling keeps rho(n) of a pixel's variance (1/2 for independent samples)
        drop = contribution * (1.0 - counts.rho_at(n))
        need = (contribution.mean() - aim**2) * len(n) - drop[want].sum()
        if need > 0.0 and np.any(room & ~want):
            sigma = np.sqrt(eff * smoothed_variance(k, n))
            neyman = sigma * sigma.sum() / (len(n) * aim**2)
            order = np.flatnonzero(room & ~want)
            gain = (sigma[order] / n[order]).astype(np.float32) ** 2  # removed per ray
            order = order[np.argsort(_allocation_key(gain, neyman[order] > math.sqrt(2.0)
                                                     * n[order]), kind="stable")]
            dropped = np.cumsum(drop[order])
            rays = np.cumsum(n[order])  # doubling a pixel traces as many rays as it has
            # a round with much to go stops short of the aim (DROP_SHORT of the need):
            # Sobol's variance often falls faster than the last measured rho says, and an
            # overshoot cannot be undone, while a shortfall costs one more round. With at
            # most SHORT_NEED aim^2 to go it aims at all of it: selected pixels' drops came
            # out up to 1.25x the prediction (issue 19, measured on the shared scenes),
            # which lands at >= 0.75 aim^2, inside the calibration band ((0.7 / 0.82)^2 =
            # 0.73), and the shortfall round it saves has a fixed cost (launches, this
            # allocation over every hit pixel; sponza at 0.05 went from 5 rounds to 3,
            # 1.25x to 1.17x the time of the fixed render of its RMSE). A round that
            # would be small (under TAIL_ROUND of the rays so far) aims TAIL_MARGIN aim^2
            # past the need (an exact prediction falls short half the time, and each
            # shortfall is one more tail: sponza at 0.05 had two) and traces at least
            # MIN_ROUND of the rays so far
            short = DROP_SHORT if need > SHORT_NEED * aim**2 * len(n) else 1.0
            end = _first(dropped >= short * need)
            so_far = float(n.sum())
            if rays[end] < TAIL_ROUND * so_far:
                end = max(_first(dropped >= need + TAIL_MARGIN * aim**2 * len(n)),
                          _first(rays >= MIN_ROUND * so_far))
            want[order[: end + 1]] = True
            # a round that would double most of the image doubles all of it (the pixels
            # left out would be the next round's, with its own fixed cost), unless that
            # could land below FULL_ROUND_AIM of the aim (the calibration band) if the
            # variance fell as fast as Sobol's can (RHO_MIN), not as fast as measured
            fastest = contribution.sum() - (1.0 - RHO_MIN) * contribution[room].sum()
            if (rays[end] >= FULL_ROUND * rays[-1]
                    and fastest >= (FULL_ROUND_AIM * aim) ** 2 * len(n)):
                want[order] = True
    return np.flatnonzero(want)


def _allocation_key(gain: np.ndarray, under: np.ndarray) -> np.ndarray:
    """Sort keys (int16, which numpy's stable sort orders by radix) for doublings: those
    `under` the Neyman count first, then by the variance removed per ray, `gain` (positive
    float32), in steps of 1/16 octave (ties in the given order)."""
    # a positive float32's bits grow with it: sign 0, then 8 exponent bits, then mantissa
    octave16 = gain.view(np.int32) >> 19  # 12 bits: exponent and the mantissa's first 4
    return (np.int16(4095) - octave16.astype(np.int16)
            + np.where(under, 0, 4096).astype(np.int16))


def _first(condition: np.ndarray) -> int:
    """Index of the first True (the last index when there is none)."""
    return int(np.argmax(condition)) if condition.any() else len(condition) - 1


def _occlusion_round(bvh, hits, pix, active, first, count, sampler_id, seed, dist,
                     nthreads, mid, quarter) -> tuple[np.ndarray, ...]:
    """Trace samples first..first+count-1 of the `active` hit pixels: per active pixel, the
    open samples, and those among them with index below `mid` and below `quarter`. The
    rays are split between host threads at pixel boundaries (a CPU launch runs on one
    thread)."""
    device = bvh.device
    m = len(active)
    act = wp.array(active.astype(np.int32), dtype=int, device=device)
    outs = [wp.zeros(m, dtype=int, device=device) for _ in range(3)]
    # More parts than threads, taken in turn (`run_parts`): a round's pixels cost very
    # different amounts (an adaptive round's are clustered where the image is noisy).
    spread = nthreads * PARTS_PER_THREAD if nthreads > 1 else 1
    parts = max(1, min(spread, m * count // PART_RAYS, m), -(-m * count // LAUNCH_RAYS))
    bounds = np.linspace(0, m, parts + 1).astype(int)

    launch = part_launcher(occlusion_kernel, [
        bvh.arrays, hits.surfaces, pix, act, 0, int(first), int(count), sampler_id, seed, dist,
        1, int(mid), int(quarter), *outs], device)

    def run(p: int) -> None:
        launch(int(bounds[p + 1] - bounds[p]) * count, {4: int(bounds[p])})

    run_parts(run, parts, nthreads)
    return tuple(out.numpy().astype(np.int64) for out in outs)


def _occlusion_round_dacrt(bvh, hits, pix, active, first, count, sampler_id, seed, dist,
                           nthreads, mid, quarter) -> tuple[np.ndarray, ...]:
    """`_occlusion_round` with the round's rays traced by DACRT (closest hit within the AO
    distance: occluded if there is one)."""
    m = len(active)
    origins, dirs = _occlusion_rays(hits, first, count, seed, sampler_id, active)
    h = dacrt_trace_mesh(scene_mesh(bvh), origins, dirs, 0.0, dist)
    opened = (h.triangle < 0).reshape(m, count)
    return tuple(opened[:, : max(0, k - first)].sum(axis=1) for k in (first + count, mid,
                                                                        quarter))


def sampler_efficiency(open_mid: np.ndarray, n_mid: np.ndarray, open_end: np.ndarray,
                       n_end: np.ndarray, default: float = 1.0) -> float:
    """The sampler's variance relative to independent samples, pooled over pixels.

    For nested estimates m_mid (first n_mid samples) and m_end (all n_end), independent
    samples give E[(m_mid - m_end)^2] = Var(m_end) (n_end - n_mid) / n_mid; a stratified
    (Sobol) sequence gives less. The ratio of the summed squared differences to the summed
    Bernoulli variances p(1-p)(n_end - n_mid)/(n_mid n_end) estimates Var(sampler) /
    Var(independent) at this sample count. Only pixels whose samples disagree take part
    (fully open or occluded ones would pull it toward 0). Clipped to [EFFICIENCY_MIN, 1];
    `default` when too few pixels disagree to tell."""
    diff2, bernoulli, mixed = _spread_sums(open_mid, n_mid, open_end, n_end)
    if mixed < EFFICIENCY_PIXELS:
        return float(default)
    return float(np.clip(diff2 / bernoulli, EFFICIENCY_MIN, 1.0))


def _spread_sums(open_mid: np.ndarray, n_mid: np.ndarray | int, open_end: np.ndarray,
                 n_end: np.ndarray | int) -> np.ndarray:
    """`sampler_efficiency`'s sums over the disagreeing pixels: (squared differences,
    Bernoulli variances, pixels), so that measurements of one count can be pooled. The
    counts are per pixel or one for all (a round's: no array of copies)."""
    mixed = np.flatnonzero((open_end > 0) & (open_end < n_end) & (n_mid > 0)
                           & (n_end > n_mid))
    if not len(mixed):
        return np.zeros(3)

    def take(x: np.ndarray | int) -> np.ndarray | float:
        return x[mixed].astype(np.float64) if np.ndim(x) else float(x)

    n_mid, n_end = take(n_mid), take(n_end)
    p = open_end[mixed] / n_end
    diff2 = (open_mid[mixed] / n_mid - p) ** 2
    bernoulli = p * (1.0 - p) * ((n_end - n_mid) / (n_mid * n_end))
    return np.array([diff2.sum(), np.sum(bernoulli), float(len(mixed))])


def sample_variance(open_count: np.ndarray, n: np.ndarray) -> np.ndarray:
    """The unbiased sample variance of each pixel's n 0/1 samples (0 where they agree)."""
    n = n.astype(np.float64)
    p = open_count / n
    return p * (1.0 - p) * n / np.maximum(n - 1.0, 1.0)


def posterior_variance(open_count: np.ndarray, n: np.ndarray, efficiency: np.ndarray
                       ) -> np.ndarray:
    """E[p(1-p) | k of n open] per pixel under a Beta(a, b) prior on the pixels' p fitted
    to the image by moments (empirical Bayes): about the sample variance where samples
    disagree, and not 0 where they agree, by as much as the image says pixels like it
    vary. The prior's spread is the spread of the estimates less their sampling
    variance (efficiency * s^2 / n)."""
    k = open_count.astype(np.float64)
    n = n.astype(np.float64)
    p = k / n
    mean = float(p.mean())
    spread = float(p.var() - np.mean(efficiency * sample_variance(open_count, n) / n))
    if not (0.0 < mean < 1.0) or spread <= 0.0:
        return sample_variance(open_count, n)
    total = max(mean * (1.0 - mean) / spread - 1.0, 1e-6)
    a, b = mean * total, (1.0 - mean) * total
    return (a + k) * (b + n - k) / ((a + b + n) * (a + b + n + 1.0))


def smoothed_variance(open_count: np.ndarray, n: np.ndarray) -> np.ndarray:
    """`sample_variance`, but where all n samples agreed p(1-p) at the Jeffreys posterior
    mean p = (k + 1/2) / (n + 1) (Brown, Cai and DasGupta 2001), about 1/(2n): an occluder
    smaller than ~1/n of the hemisphere is still possible."""
    q = (open_count + 0.5) / (n + 1.0)
    agree = (open_count == 0) | (open_count == n)
    return np.where(agree, q * (1.0 - q), sample_variance(open_count, n))


def half_width(open_count: np.ndarray, n: np.ndarray, efficiency: float | np.ndarray
               ) -> np.ndarray:
    """95% half-width of each pixel's estimate, z * sqrt(efficiency * s^2 / n), with the
    `smoothed_variance` (never 0). `efficiency` (<= 1, one or per pixel) is the sampler's
    variance relative to independent samples (`sampler_efficiency`)."""
    return Z95 * np.sqrt(efficiency * smoothed_variance(open_count, n) / n)


def _progress(mse0: float, mse: float, aim: float) -> float:
    """How far the error has come from mse0 towards aim^2, on a log scale, in [0, 1]. In
    logs apart: for a tiny target aim^2 underflows to 0."""
    if not (mse > aim * aim and mse0 > mse > 0.0):
        return 1.0 if mse <= aim * aim else 0.0
    span = math.log(mse0) - 2.0 * math.log(aim)
    return min(1.0, (math.log(mse0) - math.log(mse)) / span)


def _fraction(n_done, active, count) -> float:
    """Progress with max_pixel_error: samples done over samples planned (planned grows, so
    this is an estimate, never above 1)."""
    done = float(n_done.sum())
    planned = done + float(active * count)
    return min(done / planned, 1.0) if planned > 0 else 0.0


def ambient_occlusion(
    bvh: Bvh | Scene,
    origins: np.ndarray,
    directions: np.ndarray,
    spp: int = 16,
    distance: float | None = None,
    seed: int = 0,
    target_error: float | None = None,
    *,
    max_pixel_error: float | None = None,
    tmin: float | np.ndarray = 0.0,
    tmax: float | np.ndarray = np.inf,
    threads: int | None = None,
    max_spp: int = DEFAULT_MAX_SPP,
    sampler: str = "sobol",
    engine: str = "bvh",
    normals: np.ndarray | None = None,
    terminator_offset: float | np.ndarray = DEFAULT_TERMINATOR_OFFSET,
) -> np.ndarray:
    """AO per primary ray, (R,) float32: `render_ao(...).ao` (see there)."""
    return render_ao(bvh, origins, directions, spp, distance, seed, target_error,
                     max_pixel_error=max_pixel_error, tmin=tmin,
                     tmax=tmax, threads=threads, max_spp=max_spp, sampler=sampler,
                     engine=engine, normals=normals, terminator_offset=terminator_offset).ao


WARP_MODULES = (occlusion_kernel.module,)  # this module's kernels (core.launch.load_modules)
