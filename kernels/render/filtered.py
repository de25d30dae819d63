"""AO of a camera's image through the Film's pixel filter, as Cycles renders it: every sample
traces its own camera ray from a sub-pixel position drawn from the filter (film.py), then
one occlusion ray from that ray's hit. `render_film` returns the filtered AO and the
filtered coverage (alpha) per pixel.

Each sample's value is that of `render_ao`'s pixel for its own camera ray: V(p, w) for a
hit, 1.0 for a miss; alpha counts the samples that hit. Both are means over the pixel's
samples, so they converge to the filter-weighted integrals Cycles' film converges to.
Sample i of pixel k uses point i of the pixel's Sobol (or random) sequence for its
sub-pixel position (with the filter's own scramble) and for its occlusion direction.

Scope today: a fixed `spp` (no error target), engine "bvh", no denoising; each pixel is one
thread's, so the result is bit-identical for any `threads`. `filter_width=0` is today's
pixel-centre render: `render_ao` over `Camera.rays()`, alpha 0 or 1.
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
from .ao import default_distance, render_ao
from .camera import Camera
from .film import check_filter, filter_position, filter_table
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
    half_size: wp.vec2  # (W / 2, H / 2)
    pix: float  # image-plane size of a pixel
    shift: wp.vec2  # (shift_x, shift_y) * plane_scale
    persp: int  # 1: PERSP (plane at z = -1), 0: ORTHO (plane at z = 0)
    clip_start: float
    clip_end: float


@wp.func
def camera_ray(cam: FilmCamera, px: float, py: float):
    """(origin, unit direction, tmin, tmax) through raster point (px, py) (pixels from the
    image's left and top edges), as `Camera.rays` builds them."""
    x = (px - cam.half_size[0]) * cam.pix + cam.shift[0]
    y = (cam.half_size[1] - py) * cam.pix + cam.shift[1]
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
    """A filtered render of a camera's image, row-major with row 0 at the top."""

    ao: np.ndarray  # (H, W) float32: the mean of the samples' values
    alpha: np.ndarray  # (H, W) float32: the fraction of samples that hit (coverage)
    spp: int  # samples per pixel


def device_camera(camera: Camera) -> FilmCamera:
    """`camera` as the kernel reads it."""
    cam = FilmCamera()
    s = camera.plane_scale()
    cam.rotation = wp.mat33(*camera.rotation.astype(np.float32).ravel())
    cam.position = wp.vec3(*camera.position.astype(np.float32))
    cam.half_size = wp.vec2(0.5 * camera.width, 0.5 * camera.height)
    cam.pix = s / (camera.width if camera.horizontal_fit else camera.height)
    cam.shift = wp.vec2(camera.shift_x * s, camera.shift_y * s)
    cam.persp = 1 if camera.type == "PERSP" else 0
    cam.clip_start = camera.clip_start
    cam.clip_end = camera.clip_end
    return cam


def render_film(bvh: Bvh | Scene, camera: Camera, options: AoOptions | None = None, *,
                pixel_filter: str = "BLACKMAN_HARRIS", filter_width: float = 1.5,
                normals: Any = None, terminator_offset: float | np.ndarray | None = None,
                **settings: Any) -> FilmResult:
    """AO and alpha of `camera`'s image through the pixel filter (module docstring).
    `pixel_filter` is one of film.PIXEL_FILTERS and `filter_width` its width in pixels
    (Cycles' defaults: Blackman-Harris, 1.5), or 0 for pixel centres; the other arguments
    are `render_ao`'s."""
    opts = (options or AoOptions()).with_(**settings)
    offsets = opts.terminator_offset if terminator_offset is None else terminator_offset
    if filter_width == 0:
        o, d, t0, t1 = camera.rays()
        r = render_ao(bvh, o, d, opts, tmin=t0, tmax=t1, normals=normals,
                      terminator_offset=offsets)
        shape = (camera.height, camera.width)
        return FilmResult(ao=r.ao.reshape(shape),
                          alpha=(r.spp_used > 0).astype(np.float32).reshape(shape),
                          spp=opts.spp)
    check_filter(pixel_filter, filter_width)
    if opts.adaptive or opts.denoise or opts.engine != "bvh":
        raise ValueError("render_film renders a fixed spp with engine='bvh' and no denoising: "
                         "drop target_error, max_pixel_error, denoise and engine='dacrt', or "
                         "set filter_width=0")
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
    table = wp.array(filter_table(pixel_filter, filter_width), dtype=float, device=device)
    # Contiguous runs of pixels in host threads (a CPU launch is serial); more parts than
    # threads, taken in turn, since sky and geometry cost very different amounts.
    nthreads = host_threads(device, opts.threads)
    parts = max(1, min(nthreads * PARTS_PER_THREAD if nthreads > 1 else 1,
                       n * opts.spp // PART_RAYS, n))
    bounds = np.linspace(0, n, parts + 1).astype(int)
    wp.load_module(film_kernel.module, device=device)  # once, not in every thread at once
    launch = part_launcher(film_kernel, [
        tracer, shading, arrays, device_camera(camera), camera.width, table, opts.spp,
        SAMPLERS[opts.sampler], opts.seed, dist, 0, out_open, out_hit], device)

    def run(p: int) -> None:
        a, b = int(bounds[p]), int(bounds[p + 1])
        launch(b - a, {10: a, 11: out_open[a:b], 12: out_hit[a:b]})

    run_parts(run, parts, nthreads)
    shape = (camera.height, camera.width)
    return FilmResult(ao=(out_open.numpy() / opts.spp).astype(np.float32).reshape(shape),
                      alpha=(out_hit.numpy() / opts.spp).astype(np.float32).reshape(shape),
                      spp=opts.spp)
