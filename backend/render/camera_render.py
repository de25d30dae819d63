"""A camera render, the work of a service job and of a frame of a bundle: the scene's BVH
(cached, built or refit; of an instance list only what the camera may see), AO with
progress (through the pixel filter when the options ask for one and allow it:
AoOptions.filtered, else through the pixel centres), coverage (the filtered alpha, or 0/1
per centre), the pixel centres' depth, and the PNG."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np
from scenesort.backend.render.ao import shading
from scenesort.backend.render.bvhs import scene_bvh
from scenesort.backend.render.framing import framed
from scenesort.backend.render.visibility import View
from scenesort.backend.wire.binary import encode_png
from scenesort.backend.work.jobs import Job

from scenesort.ao_options import AoOptions

BACKGROUND_DEPTH = 1e10  # Cycles' Z pass on background pixels


def job_camera(request: Any) -> Any:
    """The framed camera of a job request (its camera, window and pixel aspect); raises
    ValueError naming the camera field at fault."""
    window = None if request.window is None else request.window.model_dump()
    return framed(request.camera.model_dump(), window, request.pixel_aspect)


def render_camera(
    job: Job,
    store: Any,
    scene: Any,
    camera: Any,
    options: AoOptions,
    method: str,
    leaf_size: int,
    device: str,
    cull: bool = True,
) -> None:
    """Render `camera`'s pixels into `job` (its ao, coverage, depth, png, build and
    statistics), reporting each phase; with `cull`, of an instance list only what the
    camera may see is built (render/bvhs.py)."""

    def timed(phase: str, fn: Callable[[], Any]) -> Any:
        job.report(phase)  # also the cancellation point between phases
        start = time.perf_counter()
        out = fn()
        job.add_timing(phase, 1000.0 * (time.perf_counter() - start))
        return out

    view = View(camera, options.distance, _reach(options)) if cull else None
    bvh, job.build = timed("bvh", lambda: scene_bvh(store, scene, method, leaf_size, device,
                                                    view))
    if not job.build.cached:  # of "bvh", the part that was Warp compiling (as "ao.compile")
        job.add_timing("bvh.compile", float(bvh.stats.compile_ms))
    origins, directions, tmin, tmax = timed("camera", camera.rays)
    shape = (camera.height, camera.width)
    job.film = options.film
    if camera.aperture_size > 0.0 and not options.filtered:
        job.film += " (no depth of field: it needs the pixel filter's own camera rays)"
    if options.filtered:
        film = timed("ao", lambda: _render_film(job, bvh, scene, camera, options))
        job.ao, job.coverage = film.ao, film.alpha
        job.spp_mean, job.spp_max = film.spp_mean, film.spp_max  # over covered pixels
        job.rmse_estimate, job.rays, job.denoised = film.rmse_estimate, film.rays, False
    else:
        result = timed("ao", lambda: _render_ao(job, bvh, scene, origins, directions, tmin,
                                                tmax, options, shape))
        job.ao = np.asarray(result.ao, dtype=np.float32).reshape(shape)
        job.coverage = (result.spp_used > 0).astype(np.float32).reshape(shape)  # misses: 0
        stats = result.stats()
        job.spp_mean, job.spp_max = stats.spp_mean, stats.spp_max
        job.rmse_estimate, job.rays = stats.rmse_estimate, stats.rays
        job.denoised = stats.denoised
    depth = timed("depth", lambda: camera_depth(bvh, camera, origins, directions, tmin, tmax))
    job.depth = depth.reshape(shape)
    job.png = timed("png", lambda: encode_png(job.ao))


def camera_depth(
    bvh: Any, camera: Any, origins: np.ndarray, directions: np.ndarray,
    tmin: np.ndarray, tmax: np.ndarray,
) -> np.ndarray:
    """Cycles' Z pass: the closest hit's camera-space depth `t * dot(d, forward)` per ray,
    BACKGROUND_DEPTH where the ray misses (the same closest-hit query as AO's primary rays)."""
    from scenesort import kernels

    hits = kernels.trace(bvh, origins, directions, tmin, tmax)
    z = hits.t.astype(np.float64) * (directions.astype(np.float64) @ camera.forward)
    return np.where(hits.hit, z, BACKGROUND_DEPTH).astype(np.float32)


def _reach(options: AoOptions) -> float:
    """How many pixels outside the image the render's camera rays start (its filter's)."""
    from scenesort.kernels.render.film import filter_reach

    return filter_reach(options.pixel_filter, options.filter_width) if options.filtered else 0.0


def _render_film(job: Job, bvh: Any, scene: Any, camera: Any, options: AoOptions) -> Any:
    """`kernels.render_film` of `camera` through the options' pixel filter with the scene's
    normals, reporting progress between its rounds; its `FilmResult`."""
    from scenesort import kernels

    def progress(fraction: float, phase: str) -> None:
        job.report(f"ao.{phase}", fraction)  # raises Stopped inside the engine's loop

    return kernels.render_film(bvh, camera, options, progress=progress, **shading(scene))


def _render_ao(
    job: Job,
    bvh: Any,
    scene: Any,
    origins: np.ndarray,
    directions: np.ndarray,
    tmin: np.ndarray,
    tmax: np.ndarray,
    options: AoOptions,
    shape: tuple[int, int],
) -> Any:
    """`kernels.render_ao` within the camera's clip range with the scene's normals,
    reporting progress between its rounds, denoised if asked (an image of `shape`); its
    `AoResult`."""
    from scenesort import kernels

    def progress(fraction: float, phase: str) -> None:
        job.report(f"ao.{phase}", fraction)  # raises Stopped inside the engine's loop

    result = kernels.render_ao(bvh, origins, directions, options, tmin=tmin, tmax=tmax,
                               progress=progress, image_shape=shape, **shading(scene))
    for name, ms in result.timings_ms.to_dict().items():
        job.add_timing(f"ao.{name}", float(ms))
    return result
