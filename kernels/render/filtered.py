"""AO of a camera's image through the Film's pixel filter, as Cycles renders it: every sample
traces its own camera ray from a sub-pixel position drawn from the filter (film.py), then
one occlusion ray from that ray's hit. `render_film` returns the filtered AO and the
filtered coverage (alpha) per pixel.

Each sample's value is that of `render_ao`'s pixel for its own camera ray: V(p, w) for a
hit, 1.0 for a miss; alpha counts the samples that hit. Both are means over the pixel's
samples, so they converge to the filter-weighted integrals Cycles' film converges to.
Sample i of pixel k uses point i of the pixel's Sobol (or random) sequence for its
sub-pixel position (with the filter's own scramble) and for its occlusion direction.

Scope today: a fixed `spp` (no error target), engine "bvh", no denoising
(`AoOptions.film_fallback`); each pixel is one thread's, so the result is bit-identical for
any `threads`. `filter_width=0` is the pixel-centre render: `render_ao` over
`Camera.rays()`, alpha 0 or 1.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import warp as wp

from scenesort.ao_options import AoOptions

from ..bvh.api import Bvh
from ..bvh.node import BvhArrays
from ..core.compile_options import MODULE_OPTIONS
from ..core.launch import PARTS_PER_THREAD, host_threads, part_launcher, run_parts
from ..core.mesh import Shading
from ..scene.api import Scene
from ..scene.top import SceneArrays, SceneShading
from .adaptive import ROUND_RAYS, Progress
from .ao import AoResult, default_distance, render_ao
from .camera import Camera
from .film import filter_position, filter_table
from .primary import scene_shading
from .sampling import SAMPLERS, cosine_direction, pixel_key
from .surface import occlusion_origin
from .tracers import PART_RAYS, MeshTracer, check_tracer, closest_surface, occluded, scene_mesh

wp.set_module_options(MODULE_OPTIONS)


@wp.struct
class FilmCamera:
    """`Camera`'s model on the device (camera.py): raster point -> camera ray."""

    rotation: wp.mat33  # matrix_world's normalised 3x3 part
    position: wp.vec3
    # Camera.raster_plane: plane x = (px - centre.x) * step.x + offset.x, y likewise
    centre: wp.vec2
    step: wp.vec2
    offset: wp.vec2
    persp: int  # 1: PERSP (plane at z = -1), 0: ORTHO (plane at z = 0)
    clip_start: float
    clip_end: float


@wp.func
def camera_ray(cam: FilmCamera, px: float, py: float):
    """(origin, unit direction, tmin, tmax) through raster point (px, py) (pixels from the
    image's left and top edges), as `Camera.rays` builds them."""
    x = (px - cam.centre[0]) * cam.step[0] + cam.offset[0]
    y = (py - cam.centre[1]) * cam.step[1] + cam.offset[1]
    if cam.persp == 1:
        world = cam.rotation * wp.vec3(x, y, -1.0)
        length = wp.length(world)
        return cam.position, world / length, cam.clip_start * length, cam.clip_end * length
    d = -wp.vec3(cam.rotation[0, 2], cam.rotation[1, 2], cam.rotation[2, 2])
    origin = cam.position + cam.rotation * wp.vec3(x, y, 0.0)
    return origin, wp.normalize(d), cam.clip_start, cam.clip_end


@wp.kernel
def film_kernel(
    tracer: Any,  # MeshTracer or SceneArrays
    shading: Any,  # Shading or SceneShading
    bvh: Any,  # BvhArrays or SceneArrays: what occlusion rays traverse
    cam: FilmCamera,
    width: int,
    table: wp.array(dtype=float),
    spp: int,
    sampler: int,
    seed: int,
    distance: float,
    pixel0: int,  # the first pixel of this launch (the outputs start there)
    out_open: wp.array(dtype=int),  # per pixel: samples whose value is 1
    out_hit: wp.array(dtype=int),  # per pixel: samples whose camera ray hit
):
    t = wp.tid()
    k = pixel0 + t
    key = pixel_key(k, seed)
    row = k / width
    col = k - row * width
    n_open = int(0)
    n_hit = int(0)
    for i in range(spp):
        offset = filter_position(table, sampler, key, i)
        o, d, t0, t1 = camera_ray(cam, float(col) + offset[0], float(row) + offset[1])
        s, hit = closest_surface(tracer, shading, o, d, t0, t1)
        if hit:
            n_hit += 1
            w = cosine_direction(s.n, sampler, key, i)
            if not occluded(bvh, occlusion_origin(s, w), w, distance, True):
                n_open += 1
        else:
            n_open += 1
    out_open[t] = n_open
    out_hit[t] = n_hit


for _tracer, _shading, _bvh in ((MeshTracer, Shading, BvhArrays),
                                (SceneArrays, SceneShading, SceneArrays)):
    wp.overload(film_kernel, {"tracer": _tracer, "shading": _shading, "bvh": _bvh})


@dataclass
class FilmResult:
    """A camera's image, row-major with row 0 at the top."""

    ao: np.ndarray  # (H, W) float32: the mean of the samples' values
    alpha: np.ndarray  # (H, W) float32: the fraction of samples that hit (coverage)
    spp: int  # samples per pixel (with filter_width=0 and an error target: the minimum)
    rays: int  # camera and occlusion rays traced
    # filter_width=0: render_ao's result over the pixel centres (its statistics, normals,
    # denoised image); None for a filtered render
    centres: AoResult | None = None


def device_camera(camera: Camera) -> FilmCamera:
    """`camera` as the kernel reads it (a framed camera too: its `raster_plane`)."""
    cam = FilmCamera()
    cam.rotation = wp.mat33(*camera.rotation.astype(np.float32).ravel())
    cam.position = wp.vec3(*camera.position.astype(np.float32))
    cam.centre, cam.step, cam.offset = (wp.vec2(*pair) for pair in camera.raster_plane())
    cam.persp = 1 if camera.type == "PERSP" else 0
    cam.clip_start = camera.clip_start
    cam.clip_end = camera.clip_end
    return cam


def render_film(bvh: Bvh | Scene, camera: Camera, options: AoOptions | None = None, *,
                normals: Any = None, terminator_offset: float | np.ndarray | None = None,
                progress: Progress | None = None, **settings: Any) -> FilmResult:
    """AO and alpha of `camera`'s image through the options' pixel filter (`pixel_filter`,
    `filter_width`; module docstring), or with filter_width=0 through the pixel centres
    (render_ao over `Camera.rays()`, any of its settings). A filter with an error target,
    denoising or engine "dacrt" raises ValueError (AoOptions.film_fallback says why).
    `normals`, `terminator_offset` and `progress` are `render_ao`'s; keywords set single
    fields of `options`."""
    opts = (options or AoOptions()).with_(**settings)
    offsets = opts.terminator_offset if terminator_offset is None else terminator_offset
    shape = (camera.height, camera.width)
    if opts.filter_width == 0.0:
        o, d, t0, t1 = camera.rays()
        r = render_ao(bvh, o, d, opts, tmin=t0, tmax=t1, normals=normals,
                      terminator_offset=offsets, image_shape=shape, progress=progress)
        return FilmResult(ao=r.ao.reshape(shape),
                          alpha=(r.spp_used > 0).astype(np.float32).reshape(shape),
                          spp=opts.min_spp, rays=r.rays.primary + r.rays.occlusion, centres=r)
    if opts.film_fallback is not None:
        raise ValueError(f"render_film with filter_width > 0 renders a fixed spp with "
                         f"engine='bvh' and no denoising: drop target_error, "
                         f"max_pixel_error, denoise and engine='dacrt', or set filter_width=0 "
                         f"({opts.film_fallback})")
    check_tracer(bvh, opts.engine)
    shading = scene_shading(bvh, normals, offsets)
    if isinstance(bvh, Scene):
        tracer, arrays = bvh.arrays, bvh.arrays
    else:
        mesh = scene_mesh(bvh)
        tracer = MeshTracer()
        tracer.bvh = bvh.arrays
        tracer.vertices, tracer.indices = mesh.v, mesh.f
        arrays = bvh.arrays
    device = bvh.device
    n = camera.width * camera.height
    out_open = wp.empty(n, dtype=int, device=device)
    out_hit = wp.empty(n, dtype=int, device=device)
    dist = default_distance(bvh) if opts.distance is None else opts.distance
    table = wp.array(filter_table(opts.pixel_filter, opts.filter_width), dtype=float,
                     device=device)
    wp.load_module(film_kernel.module, device=device)  # once, not in every thread at once
    launch = part_launcher(film_kernel, [
        tracer, shading, arrays, device_camera(camera), camera.width, table, opts.spp,
        SAMPLERS[opts.sampler], opts.seed, dist, 0, out_open, out_hit], device)
    nthreads = host_threads(device, opts.threads)
    # Rounds of about ROUND_RAYS samples (a progress call, the cancellation point, before
    # each), each in contiguous runs of pixels in host threads (a CPU launch is serial):
    # more parts than threads, taken in turn, since sky and geometry cost very different
    # amounts.
    rounds = np.linspace(0, n, max(1, min(n, n * opts.spp // ROUND_RAYS)) + 1).astype(int)
    for a, b in zip(rounds[:-1], rounds[1:], strict=True):
        if progress is not None:
            progress(float(a) / n, "film")
        m = int(b - a)
        parts = max(1, min(nthreads * PARTS_PER_THREAD if nthreads > 1 else 1,
                           m * opts.spp // PART_RAYS, m))
        bounds = np.linspace(a, b, parts + 1).astype(int)

        def run(p: int, bounds: np.ndarray = bounds) -> None:
            lo, hi = int(bounds[p]), int(bounds[p + 1])
            launch(hi - lo, {10: lo, 11: out_open[lo:hi], 12: out_hit[lo:hi]})

        run_parts(run, parts, nthreads)
    if progress is not None:
        progress(1.0, "done")
    hit = out_hit.numpy()
    return FilmResult(ao=(out_open.numpy() / opts.spp).astype(np.float32).reshape(shape),
                      alpha=(hit / opts.spp).astype(np.float32).reshape(shape),
                      spp=opts.spp, rays=n * opts.spp + int(hit.sum()))
