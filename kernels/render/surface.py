"""What occlusion rays need of a primary hit (`Surface`): the spawn point, the geometric and
shading normals and Cycles' shadow terminator lift, made on the device from the hit
triangle (of a mesh, or of an instance taken to world space).

The shading normal is the geometric normal ng turned toward the ray's origin, or with
`normals=` (one per triangle corner, as Blender's `Mesh.corner_normals`) the corners
interpolated at p (Cycles' `triangle_smooth_normal`), flipped with ng on a back face
(`shader_setup_from_ray`). For smooth triangles the occlusion ray's origin is lifted toward
the smooth surface as Cycles' `shadow_ray_offset` does (the shadow terminator geometry
offset, `terminator_offset`, default 0.1 as Blender's objects).

Guarantee: occlusion rays start at p pushed off the surface along ng by OFFSET_ULPS float32
ulps of the hit's local scale (max of |p| and the triangle's extent around p), computed in
float64 and rounded once: a flat surface never occludes itself, at any scale or offset.
(With shading normals the terminator lift is added to that point.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from ..core.compile_options import MODULE_OPTIONS
from ..core.mesh import Shading, triangle_corners
from ..scene.top import (
    InstanceHit,
    SceneArrays,
    SceneShading,
    mesh_indices,
    mesh_vertices,
    world_normal,
    world_point,
)

wp.set_module_options(MODULE_OPTIONS)

OFFSET_ULPS = 128.0  # occlusion-ray origin offset, in float32 ulps of the local scale


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
def corner_envelope(p: wp.vec3, pc: wp.vec3, pa: wp.vec3, pb: wp.vec3, nc: wp.vec3,
                    side: float) -> float:
    """One corner's term of Cycles' local linear envelope: how far the plane through corner
    pc with its normal nc, lifted over the triangle's other corners pa and pb, lies above p
    (side 1; -1: below, measured against the normals). Negating the differences is exact,
    so both sides round as Cycles' two written-out branches do."""
    lift = wp.max(wp.max(wp.dot(side * (pa - pc), nc), wp.dot(side * (pb - pc), nc)), 0.0)
    return wp.max(wp.dot(side * (pc - p), nc) + lift, 0.0)


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
    # Local linear envelope, above the normals or, seen from behind them, below
    side = wp.where(wp.dot(n, ng) > 0.0, 1.0, -1.0)
    e = wp.min(wp.min(corner_envelope(p, p0, p1, p2, n0, side),
                      corner_envelope(p, p1, p0, p2, n1, side)),
               corner_envelope(p, p2, p0, p1, n2, side))
    return n * wp.where(side > 0.0, wp.max(e, h * 0.5), wp.min(-e, h * 0.5))


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
               mirrored: bool, lifted: bool) -> Surface:
    """The spawn point, normals and terminator lift of a hit at (u, v) on the triangle
    (v0, v1, v2) (world space), with corner normals n0..n2 where `smooth` (see `Surface`).
    `mirrored`: the corners are a mirrored instance's, whose world winding is reversed.
    `lifted` False leaves `lift` zero (half a smooth surface's cost) for a caller that
    makes the surface again, lifted, for the few directions terminator_amount lifts."""
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
        if lifted:
            s.lift = smooth_surface_offset(v0, v1, v2, n0, n1, n2, u, v, s.ng)
        s.cutoff = cutoff
    return s


@wp.func
def surface(vertices: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.vec3i),
            shading: Shading, d: wp.vec3, triangle: int, u: float, v: float,
            lifted: bool) -> Surface:
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
                      False, lifted)


@wp.func
def instance_surface(scene: SceneArrays, shading: SceneShading, d: wp.vec3,
                     ih: InstanceHit, lifted: bool) -> Surface:
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
                      shading.offsets[ih.instance], wp.determinant(rec.lin) < wp.float64(0.0),
                      lifted)
