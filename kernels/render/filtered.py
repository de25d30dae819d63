"""AO of a camera's image through the Film's pixel filter, as Cycles renders it: every sample
traces its own camera ray from a sub-pixel position drawn from the filter (film.py), then
one occlusion ray from that ray's hit. `render_film` returns the filtered AO and the
filtered coverage (alpha) per pixel.

Each sample's value is that of `render_ao`'s pixel for its own camera ray: V(p, w) for a
hit, 1.0 for a miss; alpha counts the samples that hit. Both are means over the pixel's
samples, so they converge to the filter-weighted integrals Cycles' film converges to.
Sample i of pixel k uses point i of the pixel's Sobol (or random) sequence for its
sub-pixel position (with the filter's own scramble) and for its occlusion direction.

With an error target, the rounds of render_ao's adaptive controller (adaptive.py) over
the covered pixels (any of whose first `min_spp` samples hit): each sample is 0 or 1 as
an occlusion sample is, so a pixel's statistics include its edge's variance (the camera
ray hitting or not) beside its occlusion's. Engine "bvh" only, no denoising
(`AoOptions.film_fallback`); each pixel's samples in a round are one thread's, so the
result is bit-identical for any `threads`. `filter_width=0` is the pixel-centre render:
`render_ao` over `Camera.rays()`, alpha 0 or 1.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import warp as wp

from scenesort.ao_options import AoOptions

from ..bvh.api import Bvh
from ..bvh.node import BvhArrays
from ..bvh.packet import PACKET
from ..bvh.wide_traversal import simd_lanes
from ..core.compile_options import MODULE_OPTIONS
from ..core.launch import host_threads, part_launcher, run_parts
from ..core.mesh import Shading
from ..scene.api import Scene
from ..scene.top import SceneArrays, SceneShading
from .adaptive import Progress, SampleCounts, nested_marks, round_bounds, sample_rounds
from .ao import AoResult, _monotone, default_distance, render_ao
from .camera import Camera
from .film import FILTER_KEY, decorrelated_2d, filter_position, filter_table
from .primary import scene_shading
from .sampling import SAMPLERS, cosine_about, cosine_direction, pixel_key
from .surface import Surface, occlusion_origin
from .tracers import (
    PART_RAYS,
    GroupRays,
    MeshTracer,
    PacketRays,
    add_group_ray,
    check_tracer,
    closest_surface,
    closest_t,
    group_rays,
    occluded,
    occluded_group,
    open_sample,
    packet_closest,
    packet_occlusion_origin,
    packet_rays,
    packet_surface,
    scene_mesh,
)

wp.set_module_options(MODULE_OPTIONS)

LENS_KEY = wp.constant(wp.uint32(0x68E31DA4))  # separates the lens's scramble from the others'


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
    aperture: float  # the lens's radius (0: a pinhole); the others are Camera's fields
    focus: float
    blades: int
    blade_rotation: float
    inv_ratio: float


@wp.func
def concentric_disk(u: wp.vec2) -> wp.vec2:
    """A point of the unit disk for u in the unit square, area-preserving (Shirley and
    Chiu 1997): uniform for uniform u, strata kept."""
    a = 2.0 * u[0] - 1.0
    b = 2.0 * u[1] - 1.0
    if a == 0.0 and b == 0.0:
        return wp.vec2(0.0, 0.0)
    r = b
    phi = 0.5 * wp.pi - 0.25 * wp.pi * (a / b)
    if wp.abs(a) > wp.abs(b):
        r = a
        phi = 0.25 * wp.pi * (b / a)
    return wp.vec2(r * wp.cos(phi), r * wp.sin(phi))


@wp.func
def polygon_point(corners: int, rotation: float, u: wp.vec2) -> wp.vec2:
    """A uniform point of the regular polygon with `corners` corners on the unit circle,
    turned by `rotation` (Cycles' regular_polygon_sample: a corner's triangle picked by
    u.x, a uniform point in it)."""
    n = float(corners)
    corner = wp.floor(u[0] * n)
    s = wp.sqrt(u[0] * n - corner)
    t = u[1] * s
    s = 1.0 - s
    half = wp.pi / n
    p = wp.vec2((s + t) * wp.cos(half), (s - t) * wp.sin(half))
    angle = rotation + corner * 2.0 * half
    c = wp.cos(angle)
    sn = wp.sin(angle)
    return wp.vec2(c * p[0] - sn * p[1], sn * p[0] + c * p[1])


@wp.func
def lens_point(cam: FilmCamera, lens: wp.vec2) -> wp.vec3:
    """The camera-space point of the aperture that `lens` (in the unit square) picks
    (Cycles' camera_sample_aperture times its aperturesize)."""
    uv = concentric_disk(lens)
    if cam.blades > 0:
        uv = polygon_point(cam.blades, cam.blade_rotation, lens)
    return wp.vec3(uv[0] * cam.inv_ratio * cam.aperture, uv[1] * cam.aperture, 0.0)


@wp.func
def camera_ray(cam: FilmCamera, px: float, py: float, lens: wp.vec2):
    """(origin, unit direction, tmin, tmax) through raster point (px, py) (pixels from the
    image's left and top edges), as `Camera.rays` builds them; with an aperture, from the
    lens point that `lens` picks, through the point in focus of the ray the pinhole would
    trace (Cycles' camera_sample_perspective, whose clip range stays the centre ray's, and
    camera_sample_orthographic, whose ray starts at the near plane and runs as far as the
    clip range is long)."""
    x = (px - cam.centre[0]) * cam.step[0] + cam.offset[0]
    y = (py - cam.centre[1]) * cam.step[1] + cam.offset[1]
    if cam.persp == 1:
        plane = wp.vec3(x, y, -1.0)
        world = cam.rotation * plane
        length = wp.length(world)
        if cam.aperture > 0.0:
            p = lens_point(cam, lens)
            d = cam.rotation * (plane * cam.focus - p)
            return (cam.position + cam.rotation * p, wp.normalize(d), cam.clip_start * length,
                    cam.clip_end * length)
        return cam.position, world / length, cam.clip_start * length, cam.clip_end * length
    origin = cam.position + cam.rotation * wp.vec3(x, y, 0.0)
    if cam.aperture > 0.0:
        p = lens_point(cam, lens)
        d = wp.normalize(wp.vec3(0.0, 0.0, -cam.focus) - p)  # camera space, looking down -z
        near = cam.clip_start / -d[2]
        return (origin + cam.rotation * p, cam.rotation * d, near,
                near + (cam.clip_end - cam.clip_start))
    d = -wp.vec3(cam.rotation[0, 2], cam.rotation[1, 2], cam.rotation[2, 2])
    return origin, wp.normalize(d), cam.clip_start, cam.clip_end


@wp.func
def sample_ray(cam: FilmCamera, table: wp.array(dtype=float), sampler: int, key: wp.uint32,
               i: int, row: int, col: int):
    """(origin, direction, tmin, tmax) of sample i's camera ray in pixel (row, col)."""
    offset = filter_position(table, sampler, key, i)
    lens = wp.vec2(0.5, 0.5)  # the lens's centre: a pinhole
    if cam.aperture > 0.0:
        lens = decorrelated_2d(sampler, key, LENS_KEY, i)
    return camera_ray(cam, float(col) + offset[0], float(row) + offset[1], lens)


FILM_RAYS_SOURCE = (
    "#if !defined(__CUDA_ARCH__)\n"
    + (Path(__file__).parent / "film_rays.h").read_text().replace(
        "FILTER_KEY_VALUE", f"{int(FILTER_KEY)}u")
    + "#else\n    return 0;\n#endif\n"
)


@wp.func_native(FILM_RAYS_SOURCE)
def packet_samples_native(rotation: wp.mat33, position: wp.vec3, centre: wp.vec2,
                          step: wp.vec2, offset: wp.vec2, persp: int, aperture: float,
                          clip_start: float, clip_end: float, sampler: int,
                          table: wp.array(dtype=float), key: wp.uint32, first: int, count: int,
                          row: int, col: int, origins: wp.array(dtype=wp.vec3),
                          directions: wp.array(dtype=wp.vec3), tmin: wp.array(dtype=float),
                          tmax: wp.array(dtype=float), points: wp.array(dtype=wp.vec2),
                          first_ray: int) -> int:
    """Samples first .. first + count - 1 of pixel (row, col), from first_ray on: their
    occlusion-direction points on a CPU, and where it returns 1 their camera rays
    (film_rays.h); 0 on CUDA, nothing written."""
    ...


@wp.struct
class NoHoldout:
    """film_kernel's holdout where there is none: the overloads below on it do nothing, and
    the kernel compiled for it has no holdout code (a call of hold_packet in the kernel,
    never made, slowed the film by 5-13%)."""

    unused: int


@wp.func
def hold_packet(holdout: NoHoldout, rays: PacketRays, held_rays: PacketRays, first: int,
                last: int):
    """The holdout's closest hits of rays [first, last) into held_rays (which share the
    rays' origins, directions and ranges), each ray's range then ending at its hit."""
    pass


@wp.func(inline=False)  # a Warp overload of the one above: through a two-level scene
def hold_packet(holdout: SceneArrays, rays: PacketRays, held_rays: PacketRays,  # noqa: F811
                first: int, last: int):
    packet_closest(holdout, held_rays, first, last)
    for m in range(first, last):
        rays.tmax[m] = wp.min(rays.tmax[m], held_rays.t[m])


@wp.func
def hold_ray(holdout: NoHoldout, o: wp.vec3, d: wp.vec3, t0: float, t1: float,
             held_rays: PacketRays, k: int) -> float:
    """The distance of the holdout's closest hit along one ray (inf: none), also into
    held_rays.t at k."""
    return wp.inf


@wp.func  # a Warp overload of the one above: through a two-level scene
def hold_ray(holdout: SceneArrays, o: wp.vec3, d: wp.vec3, t0: float, t1: float,  # noqa: F811
             held_rays: PacketRays, k: int) -> float:
    t = closest_t(holdout, o, d, t0, t1)
    held_rays.t[k] = t
    return t


@wp.func
def is_held(holdout: NoHoldout, held_rays: PacketRays, k: int) -> bool:
    """Whether a sample that saw nothing met the holdout (its t at held_rays' entry k)."""
    return False


@wp.func  # a Warp overload of the one above
def is_held(holdout: SceneArrays, held_rays: PacketRays, k: int) -> bool:  # noqa: F811
    return held_rays.t[k] < wp.inf


@wp.func
def sample_surface(tracer: Any, shading: Any, holdout: Any, cam: FilmCamera,
                   table: wp.array(dtype=float), sampler: int, key: wp.uint32, first: int,
                   s: int, count: int, row: int, col: int, rays: PacketRays,
                   held_rays: PacketRays, packet0: int):
    """`closest_surface` of sample first + s's camera ray of pixel (row, col) through the
    tracer (MeshTracer or SceneArrays); with a holdout (not NoHoldout), the ray's range ends
    at the holdout's closest hit, whose t (inf: none) goes to held_rays.t at packet0 + s %
    PACKET (a miss there is held, as render_ao's holdout). On an AVX2 CPU the camera rays of
    PACKET samples at a time are traced together, at the first of them (a pixel's rays
    leave one point through a pixel or two: as coherent as rays get), and made there with
    the samples' occlusion-direction points (packet_samples_native)."""
    if simd_lanes() > 0:
        q = s % PACKET
        c = wp.min(PACKET, count - (s - q))
        if q == 0:
            if packet_samples_native(
                    cam.rotation, cam.position, cam.centre, cam.step, cam.offset, cam.persp,
                    cam.aperture, cam.clip_start, cam.clip_end, sampler, table, key, first + s,
                    c, row, col, rays.origins, rays.directions, rays.tmin, rays.tmax,
                    rays.points, packet0) == 0:
                for m in range(c):
                    o, d, t0, t1 = sample_ray(cam, table, sampler, key, first + s + m, row,
                                              col)
                    rays.origins[packet0 + m] = o
                    rays.directions[packet0 + m] = d
                    rays.tmin[packet0 + m] = t0
                    rays.tmax[packet0 + m] = t1
            hold_packet(holdout, rays, held_rays, packet0, packet0 + c)
        return packet_surface(tracer, shading, rays, packet0, packet0 + q, packet0 + c)
    o, d, t0, t1 = sample_ray(cam, table, sampler, key, first + s, row, col)
    t1 = wp.min(t1, hold_ray(holdout, o, d, t0, t1, held_rays, packet0 + s % PACKET))
    return closest_surface(tracer, shading, o, d, t0, t1)


@wp.func
def sample_direction(n: wp.vec3, sampler: int, key: wp.uint32, i: int, rays: PacketRays,
                     k: int) -> wp.vec3:
    """`cosine_direction` of sample i about n, from its point that packet_samples_native
    made at packet ray k on an AVX2 CPU."""
    if simd_lanes() > 0:
        return cosine_about(n, rays.points[k])
    return cosine_direction(n, sampler, key, i)


@wp.func
def sample_origin(tracer: Any, shading: Any, rays: PacketRays, packet0: int, s: int,
                  surface: Surface, w: wp.vec3) -> wp.vec3:
    """`occlusion_origin` toward w of `sample_surface`'s surface of sample s (whose lift a
    packet's surface leaves to packet_occlusion_origin)."""
    if simd_lanes() > 0:
        return packet_occlusion_origin(tracer, shading, rays, packet0 + s % PACKET, surface, w)
    return occlusion_origin(surface, w)


@wp.kernel
def film_kernel(
    tracer: Any,  # MeshTracer or SceneArrays
    shading: Any,  # Shading or SceneShading
    bvh: Any,  # BvhArrays or SceneArrays: what occlusion rays traverse
    holdout: Any,  # SceneArrays: what the camera sees as holdout; NoHoldout: none
    cam: FilmCamera,
    width: int,
    table: wp.array(dtype=float),
    sampler: int,
    seed: int,
    distance: float,
    active: wp.array(dtype=int),  # the pixel (row-major index) of each slot of this round
    slot0: int,  # the first slot of this launch
    first: int,  # the first sample index of this round (the same for every slot)
    count: int,  # samples per slot this round
    mid: int,  # out_open_mid counts the open samples with index below this (absolute)
    quarter: int,  # out_open_quarter: those below this
    rays: PacketRays,  # one packet per part of the round
    held_rays: PacketRays,  # the holdout's hits of the same rays (with a holdout)
    group: GroupRays,  # one group per part: the occlusion rays of the packet's hits
    packet0: int,  # this launch's packet in `rays` and group in `group`
    out_open: wp.array(dtype=int),  # per slot: samples whose value is 1
    out_open_mid: wp.array(dtype=int),
    out_open_quarter: wp.array(dtype=int),
    out_hit: wp.array(dtype=int),  # per slot: samples whose camera ray hit
    out_held: wp.array(dtype=int),  # per slot: samples whose camera ray met the holdout
    out_normal: wp.array(dtype=wp.vec3),  # per slot: the sum of its hits' shading normals
):
    # One pixel's samples per thread: each slot is written by one thread of one launch.
    j = slot0 + wp.tid()
    k = active[j]
    key = pixel_key(k, seed)
    row = k / width
    col = k - row * width
    opened = wp.vec3i(0, 0, 0)  # open samples: all, below mid, below quarter
    n_hit = int(0)
    n_held = int(0)
    normal = wp.vec3(0.0)  # Cycles' Normal pass: the hits' normals over all samples
    # The occlusion rays of a packet's hits go as one group at the packet's end (rays from
    # around one point: bvh/wide_occlusion.h).
    m = int(0)
    for s in range(count):
        i = first + s
        surface, hit = sample_surface(tracer, shading, holdout, cam, table, sampler, key,
                                      first, s, count, row, col, rays, held_rays, packet0)
        if hit:
            n_hit += 1
            normal += surface.n
            w = sample_direction(surface.n, sampler, key, i, rays, packet0 + s % PACKET)
            o = sample_origin(tracer, shading, rays, packet0, s, surface, w)
            if simd_lanes() > 0:
                add_group_ray(group, packet0 + m, o, w, distance, i)
                m += 1
            elif not occluded(bvh, o, w, distance, True):  # elsewhere ray by ray
                opened += open_sample(i, mid, quarter)
        else:  # a miss counts 1, as render_ao's pixels do; so does a held sample
            opened += open_sample(i, mid, quarter)
            if is_held(holdout, held_rays, packet0 + s % PACKET):
                n_held += 1
        if m > 0 and (s % PACKET == PACKET - 1 or s == count - 1):
            occluded_group(bvh, group, packet0, packet0 + m)
            for g in range(packet0, packet0 + m):
                if group.triangle[g] < 0:
                    opened += open_sample(group.sample[g], mid, quarter)
            m = 0
    out_open[j] = opened[0]
    out_open_mid[j] = opened[1]
    out_open_quarter[j] = opened[2]
    out_hit[j] = n_hit
    out_held[j] = n_held
    out_normal[j] = normal


# a holdout comes with a two-level scene (a mesh's is rendered as one: render_film)
for _tracer, _shading, _bvh, _holdout in ((MeshTracer, Shading, BvhArrays, NoHoldout),
                                          (SceneArrays, SceneShading, SceneArrays, NoHoldout),
                                          (SceneArrays, SceneShading, SceneArrays, SceneArrays)):
    wp.overload(film_kernel, {"tracer": _tracer, "shading": _shading, "bvh": _bvh,
                              "holdout": _holdout})


@dataclass
class FilmResult:
    """A camera's image, row-major with row 0 at the top."""

    ao: np.ndarray  # (H, W) float32: the mean of the samples' values
    alpha: np.ndarray  # (H, W) float32: the fraction of samples that hit (coverage)
    spp_used: np.ndarray  # (H, W) int32: samples per pixel (pixel centres: 0 on a miss)
    rays: int  # camera and occlusion rays traced
    # the estimated RMSE of `ao` over the covered pixels (alpha > 0) against the converged
    # image, as render_ao's (adaptive.py); None when nothing is covered
    rmse_estimate: float | None
    # (H, W, 3) float32: Cycles' Normal pass, the sum of the samples' unit shading normals
    # (0 for a miss or a held sample) over the samples: a pixel centre's normal with
    # filter_width=0; through a filter an edge pixel's is shorter, as its alpha is less than 1
    normals: np.ndarray
    # filter_width=0: render_ao's result over the pixel centres (its statistics, normals,
    # denoised image); None for a filtered render
    centres: AoResult | None = None
    # (H, W) float32: the fraction of samples whose camera ray met the holdout before
    # anything seen (those count as misses in ao and alpha); None without a holdout
    holdout: np.ndarray | None = None

    @property
    def spp_mean(self) -> float:
        """Mean samples over the covered pixels (0 when none is)."""
        covered = self.spp_used[self.alpha > 0]
        return float(covered.mean()) if covered.size else 0.0

    @property
    def spp_max(self) -> int:
        """Most samples a covered pixel took (0 when none is)."""
        covered = self.spp_used[self.alpha > 0]
        return int(covered.max()) if covered.size else 0


def device_camera(camera: Camera) -> FilmCamera:
    """`camera` as the kernel reads it (a framed camera too: its `raster_plane`)."""
    cam = FilmCamera()
    cam.rotation = wp.mat33(*camera.rotation.astype(np.float32).ravel())
    cam.position = wp.vec3(*camera.position.astype(np.float32))
    cam.centre, cam.step, cam.offset = (wp.vec2(*pair) for pair in camera.raster_plane())
    cam.persp = 1 if camera.type == "PERSP" else 0
    cam.clip_start = camera.clip_start
    cam.clip_end = camera.clip_end
    cam.aperture = camera.aperture_size
    cam.focus = camera.focus_distance
    cam.blades = camera.aperture_blades
    cam.blade_rotation = camera.aperture_rotation
    cam.inv_ratio = 1.0 / camera.aperture_ratio
    return cam


# Pixels go to the kernels in square tiles of TILE: the rays of a tile's pixels meet the
# same nodes and leaves, which stay in the cache between them. Issue 33's six Suzannes (1.5M
# triangles, 320x240, 64 spp): 5-7% faster than rows, the same image; 8 and Morton order
# gave about as much, 4 less; the shared scenes' trees (<= 1.1M triangles, 16 spp) neither
# gain nor lose.
TILE = 16
# Parts per host thread of a film's round (core.launch's PARTS_PER_THREAD is 8): a round
# ends when its last part does, and a film's parts cost unevenly (sky, ground, detail).
# Issue 33's six Suzannes, two threads: 0.672 s against 0.689 (means of 5 processes).
FILM_PARTS_PER_THREAD = 32


def tile_order(width: int, height: int) -> np.ndarray:
    """The row-major indices of a width x height image's pixels, tile by tile (TILE x TILE
    tiles in rows, the pixels of each in rows; tiles at the right and bottom edges may be
    smaller)."""
    row, col = np.arange(height), np.arange(width)
    tiles_across = -(-width // TILE)
    key = ((row // TILE * tiles_across)[:, None] + (col // TILE)[None, :]) * (TILE * TILE)
    key += (row % TILE * TILE)[:, None] + (col % TILE)[None, :]
    return np.argsort(key.ravel(), kind="stable")


def render_film(bvh: Bvh | Scene, camera: Camera, options: AoOptions | None = None, *,
                normals: Any = None, terminator_offset: float | np.ndarray | None = None,
                occluders: Bvh | Scene | None = None, holdout: Bvh | Scene | None = None,
                progress: Progress | None = None, **settings: Any) -> FilmResult:
    """AO and alpha of `camera`'s image through the options' pixel filter (`pixel_filter`,
    `filter_width`; module docstring), or with filter_width=0 through the pixel centres
    (render_ao over `Camera.rays()`, any of its settings). A filter with denoising or
    engine "dacrt" raises ValueError (AoOptions.film_fallback says why). With an error
    target the rounds are render_ao's (adaptive.py) over the covered pixels: those that
    any of their first `min_spp` samples hit. `normals`, `terminator_offset`, `occluders`
    (what occlusion rays meet; None: `bvh`; of `bvh`'s kind), `holdout` (what the camera
    sees as holdout; of `bvh`'s kind, through a filter Scenes only: FilmResult.holdout) and
    `progress` are `render_ao`'s; keywords set single fields of `options`."""
    opts = (options or AoOptions()).with_(**settings)
    offsets = opts.terminator_offset if terminator_offset is None else terminator_offset
    shape = (camera.height, camera.width)
    if opts.filter_width == 0.0:
        o, d, t0, t1 = camera.rays()
        r = render_ao(bvh, o, d, opts, tmin=t0, tmax=t1, normals=normals,
                      terminator_offset=offsets, image_shape=shape, progress=progress,
                      occluders=occluders, holdout=holdout)
        return FilmResult(ao=r.ao.reshape(shape),
                          alpha=(r.spp_used > 0).astype(np.float32).reshape(shape),
                          spp_used=r.spp_used.reshape(shape),
                          rays=r.rays.primary + r.rays.occlusion,
                          rmse_estimate=r.rmse_estimate, centres=r,
                          normals=r.normals.reshape(*shape, 3),
                          holdout=None if r.holdout is None
                          else r.holdout.astype(np.float32).reshape(shape))
    if opts.film_fallback is not None:
        raise ValueError(f"render_film with filter_width > 0 renders with engine='bvh' and "
                         f"no denoising: drop denoise and engine='dacrt', or set "
                         f"filter_width=0 ({opts.film_fallback})")
    check_tracer(bvh, opts.engine)
    for name, other in (("occluders", occluders), ("holdout", holdout)):
        if other is not None and (type(other) is not type(bvh) or other.device != bvh.device):
            raise ValueError(f"{name} must be of bvh's kind (both a Bvh or both a Scene) and "
                             "on its device")
    if holdout is not None and not isinstance(bvh, Scene):
        raise ValueError("holdout through a pixel filter needs two-level scenes (bvh and "
                         "holdout from kernels.build_scene), or set filter_width=0")
    report = _monotone(progress)
    order = tile_order(camera.width, camera.height)
    trace = _film_tracer(bvh, camera, opts, normals, offsets, occluders or bvh, holdout,
                         order)
    n, m = camera.width * camera.height, opts.min_spp
    # The first m samples of every pixel, in rounds of about ROUND_RAYS samples (a progress
    # call, the cancellation point, before each): they find the covered pixels (with a
    # fixed spp, all the work).
    first_open, first_mid, first_quarter, hits, held = (np.zeros(n, np.int64)
                                                         for _ in range(5))
    normal_sum = np.zeros((n, 3))
    mid, quarter = nested_marks(0, m)
    share = 0.5 if opts.adaptive else 1.0  # of the progress bar
    bounds = round_bounds(n, m)
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        report(share * float(a) / n, "film")
        pixels = order[a:b]
        (first_open[pixels], first_mid[pixels], first_quarter[pixels], hits[pixels],
         held[pixels], normal_sum[pixels]) = trace(pixels, 0, m, mid, quarter)
    covered = np.flatnonzero(hits)

    def trace_round(select: np.ndarray, first: int, count: int, mid: int,
                    quarter: int) -> tuple[np.ndarray, ...]:
        pixels = covered[select]
        if first == 0:  # traced above
            return first_open[pixels], first_mid[pixels], first_quarter[pixels]
        opened, opened_mid, opened_quarter, hit, held_here, normal_here = trace(
            pixels, first, count, mid, quarter)
        hits[pixels] += hit
        held[pixels] += held_here
        normal_sum[pixels] += normal_here
        return opened, opened_mid, opened_quarter

    counts = SampleCounts(*(np.zeros(len(covered), np.int64) for _ in range(3)),
                          threads=opts.threads)
    if len(covered):
        counts.trace(trace_round, np.arange(len(covered)), m)

    def rounds_progress(fraction: float, phase: str) -> None:
        report(share + (1.0 - share) * fraction, "film")

    counts, _ = sample_rounds(trace_round, len(covered), opts, rounds_progress, counts)
    report(1.0, "done")
    done = np.full(n, m, np.int64)
    done[covered] = counts.done
    opened = first_open.copy()
    opened[covered] = counts.open
    return FilmResult(ao=(opened / done).astype(np.float32).reshape(shape),
                      alpha=(hits / done).astype(np.float32).reshape(shape),
                      spp_used=done.astype(np.int32).reshape(shape),
                      rays=int(done.sum() + hits.sum()),
                      rmse_estimate=math.sqrt(counts.mse()) if len(covered) else None,
                      normals=(normal_sum / done[:, None]).astype(np.float32).reshape(
                          *shape, 3),
                      holdout=None if holdout is None
                      else (held / done).astype(np.float32).reshape(shape))


def _tracer(bvh: Bvh | Scene) -> MeshTracer | Any:
    """What film_kernel traces camera rays through: a Scene's arrays, a mesh's tracer."""
    if isinstance(bvh, Scene):
        return bvh.arrays
    mesh = scene_mesh(bvh)
    tracer = MeshTracer()
    tracer.bvh = bvh.arrays
    tracer.vertices, tracer.indices = mesh.v, mesh.f
    return tracer


def _film_tracer(bvh: Bvh | Scene, camera: Camera, opts: AoOptions, normals: Any,
                 offsets: Any, occluders: Bvh | Scene, holdout: Bvh | Scene | None,
                 order: np.ndarray) -> Callable[..., tuple[np.ndarray, ...]]:
    """trace(pixels, first, count, mid, quarter): samples first..first+count-1 of these
    pixels (row-major indices), each through its own filtered camera ray into `bvh` (its
    range ending at `holdout`'s closest hit) and an occlusion ray through `occluders`: per
    pixel its open samples, those with index below mid and below quarter, its hits, its
    held samples and the sum of its hits' shading normals ((k, 3)). The kernels get the
    pixels in `order` (tile_order's)."""
    shading = scene_shading(bvh, normals, offsets)
    arrays = occluders.arrays
    tracer = _tracer(bvh)
    device = bvh.device
    dist = default_distance(bvh) if opts.distance is None else opts.distance
    table = wp.array(filter_table(opts.pixel_filter, opts.filter_width), dtype=float,
                     device=device)
    wp.load_module(film_kernel.module, device=device)  # once, not in every thread at once
    nthreads = host_threads(device, opts.threads)
    head = [tracer, shading, arrays, NoHoldout() if holdout is None else holdout.arrays,
            device_camera(camera), camera.width, table, SAMPLERS[opts.sampler], opts.seed,
            dist]
    kept: list[tuple[PacketRays, PacketRays, GroupRays]] = []

    def packets(parts: int) -> tuple[PacketRays, PacketRays, GroupRays]:
        """One packet, its holdout's hits and one group per part, kept for the render's
        later rounds."""
        if not kept or kept[0][0].t.shape[0] < parts * PACKET:
            rays = packet_rays(parts, isinstance(bvh, Scene), device)
            held = rays  # not read without a holdout
            if holdout is not None:
                held = packet_rays(parts, isinstance(holdout, Scene), device)
                held.origins, held.directions = rays.origins, rays.directions
                held.tmin, held.tmax = rays.tmin, rays.tmax
            kept[:] = [(rays, held, group_rays(parts, isinstance(occluders, Scene), device))]
        return kept[0]

    tile_rank = np.argsort(order)

    def trace(pixels: np.ndarray, first: int, count: int, mid: int,
              quarter: int) -> tuple[np.ndarray, ...]:
        """Any pixels, traced tile by tile (TILE), the results in `pixels`' order."""
        k = len(pixels)
        tiled = np.argsort(tile_rank[pixels], kind="stable")
        active = wp.array(pixels[tiled].astype(np.int32), dtype=int, device=device)
        outs = [*(wp.empty(k, dtype=int, device=device) for _ in range(5)),
                wp.empty(k, dtype=wp.vec3, device=device)]
        # Contiguous runs of pixels in host threads (a CPU launch is serial): more parts
        # than threads, taken in turn, since sky and geometry cost very different amounts.
        parts = max(1, min(nthreads * FILM_PARTS_PER_THREAD if nthreads > 1 else 1,
                           k * count // PART_RAYS, k))
        bounds = np.linspace(0, k, parts + 1).astype(int)
        launch = part_launcher(film_kernel, [*head, active, 0, int(first), int(count),
                                             int(mid), int(quarter), *packets(parts), 0, *outs],
                               device)

        def run(p: int) -> None:
            launch(int(bounds[p + 1] - bounds[p]), {11: int(bounds[p]), 19: p * PACKET})

        run_parts(run, parts, nthreads)
        results = []
        for out in outs:  # counts as int64, normal sums as float64: summed over rounds
            values = out.numpy()
            results.append(np.empty(values.shape, np.float64 if values.ndim > 1 else np.int64))
            results[-1][tiled] = values
        return tuple(results)

    return trace
