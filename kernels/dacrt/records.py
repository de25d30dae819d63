"""What both DACRT variants share about rays and triangles: the ray record that the box and
plane tests read, the triangles by id, the packed closest-hit key per ray, and the kernels
that prepare them and unpack the answer.

Boxes and ray spans are widened by a margin (`margin_for`), so no hit that the watertight
test reports is lost to rounding; the hit decision and reported t are those of
`kernels.core.triangle`, so the answers equal `kernels.trace`'s.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..core.claim import Claims, claimed_items, launch_claimed
from ..core.compile_options import MODULE_OPTIONS
from ..core.device_arrays import DeviceArrays
from ..core.hits import Hits
from ..core.launch import host_threads
from ..core.mesh import DeviceMesh
from ..core.ray import Hit, make_ray, no_hit
from ..core.triangle import intersect_triangle, refine_hit

wp.set_module_options(MODULE_OPTIONS)

KEY_NONE = wp.constant(wp.uint64(0xFFFFFFFFFFFFFFFF))
MARGIN_REL = 2.0**-16  # box and plane widening, relative to the largest coordinate


@wp.struct
class RayRecord:
    """What the box and plane tests read of a ray: 32 bytes, one cache line access per ray
    in the classification phases, where rays are visited in index-array order."""

    origin: wp.vec3
    tmin: float
    inv_dir: wp.vec3  # 1/d, +-inf where d == 0 (treated as parallel to that slab)
    tmax: float


@wp.struct
class TraceArrays:
    """The rays and triangles of one trace and each ray's closest hit so far, as both
    variants read them."""

    rays: wp.array(dtype=RayRecord)  # per ray id
    directions: wp.array(dtype=wp.vec3)  # exact, for the triangle test
    tri_verts: wp.array(dtype=wp.vec3)  # v0, v1, v2 per triangle id
    tri_lo: wp.array(dtype=wp.vec3)
    tri_hi: wp.array(dtype=wp.vec3)
    best: wp.array(dtype=wp.uint64)  # per ray id: packed (t, triangle) of the closest hit
    margin: float  # widening of boxes and planes (margin_for)


@wp.func_native(
    """
union { float f; uint32_t u; } c;
c.f = t;
uint32_t b = (c.u & 0x80000000u) ? ~c.u : (c.u | 0x80000000u);
return ((uint64_t)b << 32) | (uint64_t)(uint32_t)tri;
"""
)
def hit_key(t: float, tri: int) -> wp.uint64:
    """(t, triangle) packed so that unsigned order is t order, then triangle order."""
    ...


@wp.func_native(
    """
uint32_t b = (uint32_t)(key >> 32);
union { float f; uint32_t u; } c;
c.u = (b & 0x80000000u) ? (b & 0x7FFFFFFFu) : ~b;
return c.f;
"""
)
def key_t(key: wp.uint64) -> float: ...


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    atomicMin((unsigned long long*)&a[i], (unsigned long long)v);
#else
    uint64_t old;
    __atomic_load(&a[i], &old, __ATOMIC_SEQ_CST);
    while (v < old && !__atomic_compare_exchange_n(&a[i], &old, v, false, __ATOMIC_SEQ_CST,
                                                   __ATOMIC_SEQ_CST)) {}
#endif
"""
)
def shared_min_u64(a: wp.array(dtype=wp.uint64), i: int, v: wp.uint64): ...


@wp.kernel
def prepare_rays(
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    tmin: wp.array(dtype=float),
    tmax: wp.array(dtype=float),
    rays: wp.array(dtype=RayRecord),
    claims: Claims,
):
    items = claimed_items(claims, wp.tid())
    for i in range(items[0], items[1]):
        d = directions[i]
        r = RayRecord()
        r.origin = origins[i]
        r.tmin = tmin[i]
        r.inv_dir = wp.vec3(1.0 / d[0], 1.0 / d[1], 1.0 / d[2])  # +-inf where d == 0
        r.tmax = tmax[i]
        rays[i] = r


@wp.func
def unpacked_hit(tri_verts: wp.array(dtype=wp.vec3), rec: RayRecord, direction: wp.vec3,
                 key: wp.uint64) -> Hit:
    """A ray's closest-hit key unpacked: t (and u, v) refined in float64 and clamped to the
    ray's range, as `kernels.trace` does; a miss for KEY_NONE."""
    out = Hit()  # u, v: 0
    no_hit(out)
    if key != KEY_NONE:
        tri = int(key & wp.uint64(0xFFFFFFFF))
        r = make_ray(rec.origin, direction)
        v0 = tri_verts[3 * tri]
        v1 = tri_verts[3 * tri + 1]
        v2 = tri_verts[3 * tri + 2]
        h = refine_hit(r, v0, v1, v2, rec.tmin, rec.tmax,
                       intersect_triangle(r, v0, v1, v2, rec.tmin, rec.tmax))
        out.t = h[0]
        out.triangle = tri
        out.u = h[1]
        out.v = h[2]
    return out


@wp.kernel
def write_hits(
    tri_verts: wp.array(dtype=wp.vec3),
    rays: wp.array(dtype=RayRecord),
    directions: wp.array(dtype=wp.vec3),
    best: wp.array(dtype=wp.uint64),
    out_t: wp.array(dtype=float),
    out_triangle: wp.array(dtype=int),
    out_u: wp.array(dtype=float),
    out_v: wp.array(dtype=float),
    claims: Claims,
):
    items = claimed_items(claims, wp.tid())
    for i in range(items[0], items[1]):
        h = unpacked_hit(tri_verts, rays[i], directions[i], best[i])
        out_t[i] = h.t
        out_triangle[i] = h.triangle
        out_u[i] = h.u
        out_v[i] = h.v


def margin_for(vertices: np.ndarray, origins: np.ndarray) -> float:
    """Widening that covers the watertight test's rounding: a few float32 ulps of the
    largest coordinate in play, with a generous factor."""
    big = max(max(abs(float(x.max(initial=0.0))), abs(float(x.min(initial=0.0))))
              for x in (vertices, origins))
    return MARGIN_REL * max(big, 1e-30)


def scene_box(vertices: np.ndarray, indices: np.ndarray, ids: np.ndarray,
              margin: float) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) of the vertices that the triangles `ids` use, widened by the margin (a
    column-wise reduction over one copy: numpy's min(axis=0) of an (N, 3) array ran 10x
    slower, 18 ms of a 260 ms call on the buddha)."""
    used = np.zeros(len(vertices), bool)
    used[indices[ids]] = True
    columns = np.ascontiguousarray(vertices[used].T)
    return columns.min(axis=1) - margin, columns.max(axis=1) + margin


def rays_and_triangles(mem: DeviceArrays, mesh: DeviceMesh, origins, directions, tmin,
                       tmax) -> TraceArrays:
    """The rays as both variants read them, and the mesh's triangles by id with their boxes
    (made once per mesh, and counted here as held)."""
    r = len(origins)
    d = TraceArrays()
    d.directions = mem.new(max(r, 1), wp.vec3, data=directions if r else None)
    d.rays = mem.new(max(r, 1), RayRecord)
    per_ray = [mem.new(r, dt, data=x) for x, dt in ((origins, wp.vec3), (tmin, float),
                                                   (tmax, float))]
    launch_claimed(prepare_rays, r, [per_ray[0], d.directions, *per_ray[1:], d.rays],
                   mem.device, host_threads(mem.device, None))
    mem.free(*per_ray)
    d.tri_verts, d.tri_lo, d.tri_hi = mesh.soup()
    mem.hold(mesh.v, mesh.f, d.tri_verts, d.tri_lo, d.tri_hi)
    return d


def unpack_hits(mem: DeviceArrays, d: TraceArrays, r: int) -> Hits:
    """Unpack every ray's closest-hit key (both variants), split over the host threads."""
    out = [mem.new(max(r, 1), dt) for dt in (float, int, float, float)]
    launch_claimed(write_hits, r, [d.tri_verts, d.rays, d.directions, d.best, *out],
                   mem.device, host_threads(mem.device, None))
    t, tri, u, v = (a.numpy()[:r] for a in out)
    return Hits(t=t, triangle=tri.astype(np.int32), u=u, v=v)


WARP_MODULES = (prepare_rays.module,)  # this module's kernels (see core.launch.load_modules)
