"""The primary rays: those that enter the scene box (a float64 slab test on the device), their
closest hits through the tracer (or DACRT), and the hits' `Surface`s, from which the
occlusion rays start. A primary ray that misses is not shaded (its AO is 1.0).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from scenesort.ao_options import DEFAULT_TERMINATOR_OFFSET

from ..bvh.api import Bvh
from ..core.claim import Claims, claimed_items, launch_claimed
from ..core.compile_options import MODULE_OPTIONS
from ..core.launch import host_threads
from ..core.mesh import Shading
from ..core.validate import ray_range
from ..dacrt.api import dacrt_trace_mesh
from ..scene.api import Scene
from ..scene.top import SceneShading
from .surface import PrimaryHits, Surface
from .tracers import MeshTracer, gather_surfaces, primary_kernel, scene_mesh, surface_kernel

wp.set_module_options(MODULE_OPTIONS)


@wp.func
def box_touched(lo: wp.vec3d, hi: wp.vec3d, o: wp.vec3, d: wp.vec3, tmin: float,
                tmax: float) -> int:
    """1 if the ray's [tmin, tmax] segment may touch the box: a float64 slab test, exact
    enough that the box's widening covers its rounding."""
    enter = wp.float64(tmin)
    leave = wp.float64(tmax)
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
    return wp.where(inside == 1 and enter <= leave, 1, 0)


@wp.kernel
def box_candidates_kernel(lo: wp.vec3d, hi: wp.vec3d, origins: wp.array(dtype=wp.vec3),
                          directions: wp.array(dtype=wp.vec3), tmin: wp.array(dtype=float),
                          tmax: wp.array(dtype=float), touches: wp.array(dtype=int),
                          claims: Claims):
    items = claimed_items(claims, wp.tid())
    for i in range(items[0], items[1]):
        touches[i] = box_touched(lo, hi, origins[i], directions[i], tmin[i], tmax[i])


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
    launch_claimed(box_candidates_kernel, origins.shape[0],
                   [wp.vec3d(*(lo - pad)), wp.vec3d(*(hi + pad)), origins, directions, tmin,
                    tmax, touches], origins.device, threads)
    return np.flatnonzero(touches.numpy()).astype(np.int32)


def scene_shading(bvh: Bvh | Scene, normals, terminator_offset) -> Shading | SceneShading:
    """The device shading inputs of a mesh (`DeviceMesh.shading`) or a scene
    (`Scene.shading`: normals per mesh, offsets per instance), validated and kept."""
    if isinstance(bvh, Scene):
        return bvh.shading(normals, terminator_offset)
    return scene_mesh(bvh).shading(normals, terminator_offset)


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
        launch_claimed(primary_kernel, m, [tracer, shading, *per_item, surfaces, hit], device,
                       nthreads)
    keep = np.flatnonzero(hit.numpy())
    return PrimaryHits(pixels=cand[keep], surfaces=gather_surfaces(surfaces, keep), traced=m)


def surface_hits(bvh: Bvh, triangles: np.ndarray, u: np.ndarray, v: np.ndarray, normals=None,
                 terminator_offset: float | np.ndarray = DEFAULT_TERMINATOR_OFFSET,
                 ) -> PrimaryHits:
    """Given points on the mesh's own triangles (a bake's texels) as `Surface`s seen from
    the side the triangle's winding faces, as a camera would see them; points on triangles
    without area are left out (they are never hit either)."""
    mesh = scene_mesh(bvh)
    shading = scene_shading(bvh, normals, terminator_offset)
    corners = bvh.vertices[bvh.indices[triangles]].astype(np.float64)
    ng = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    keep = np.flatnonzero(np.any(ng != 0.0, axis=1)).astype(np.int32)
    n = len(keep)
    surfaces = wp.empty(n, dtype=Surface, device=bvh.device)
    if n:
        seen_from = (-ng[keep]).astype(np.float32)  # a view ray's direction onto the front
        wp.launch(surface_kernel, dim=n, inputs=[
            mesh.v, mesh.f, shading, wp.array(seen_from, dtype=wp.vec3, device=bvh.device),
            *(wp.array(x[keep], device=bvh.device) for x in (triangles, u, v)),
        ], outputs=[surfaces], device=bvh.device)
    return PrimaryHits(pixels=keep, surfaces=surfaces, traced=0)


WARP_MODULES = (box_candidates_kernel.module,)  # this module's kernels (load_modules)
