"""A camera render, the work of a service job and of a frame of a bundle: the scene's BVH
(cached, built or refit; of an instance list only what the camera may see), AO with
progress (through the pixel filter when the options ask for one and allow it:
AoOptions.filtered, else through the pixel centres), coverage (the filtered alpha, or 0/1
per centre) and the pixel centres' depth."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from scenesort.backend.render.ao import shading
from scenesort.backend.render.bvhs import Views, scene_views
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


def job_png(job: Job) -> bytes | None:
    """A camera job's AO as an 8-bit grey PNG, encoded once; None for a job that makes no
    picture or is not done."""
    if job.png is None and job.picture and job.ao is not None:
        job.png = encode_png(job.ao)
    return job.png


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
    passes: Sequence[str] = (),
    depth: bool = True,
) -> None:
    """Render `camera`'s pixels into `job` (its ao, coverage, depth, png, build and
    statistics, and the extra `passes`: JobRequest.passes; no depth without `depth`),
    reporting each phase; with
    `cull`, of an instance list only what the camera may see is built (render/bvhs.py)."""

    view = View(camera, options.distance, _reach(options)) if cull else None
    views, job.build = job.timed("bvh", lambda: scene_views(store, scene, method, leaf_size,
                                                            device, view))
    if not job.build.cached:  # of "bvh", the part that was Warp compiling (as "ao.compile")
        job.add_timing("bvh.compile", float(views.camera.stats.compile_ms))
    shape = (camera.height, camera.width)
    filtered = options.filtered
    job.film = options.film
    if camera.aperture_size > 0.0 and not filtered:
        job.film += " (no depth of field: it needs the pixel filter's own camera rays)"
    if filtered:
        film = job.timed("ao", lambda: _render_film(job, views, scene, camera, options))
        job.ao, job.coverage = film.ao, film.alpha
        job.spp_mean, job.spp_max = film.spp_mean, film.spp_max  # over covered pixels
        job.rmse_estimate, job.rays, job.denoised = film.rmse_estimate, film.rays, False
        normals, held = film.normals, film.holdout
    else:
        origins, directions, tmin, tmax = job.timed("camera", camera.rays)
        result = job.timed(
            "ao", lambda: _render_ao(job, views, scene, origins, directions, tmin, tmax,
                                     options, shape)
        )
        job.ao = np.asarray(result.ao, dtype=np.float32).reshape(shape)
        # misses and holdouts: 0 spp
        job.coverage = (result.spp_used > 0).astype(np.float32).reshape(shape)
        stats = result.stats()
        job.spp_mean, job.spp_max = stats.spp_mean, stats.spp_max
        job.rmse_estimate, job.rays = stats.rmse_estimate, stats.rays
        job.denoised = stats.denoised
        normals, held = result.normals, result.holdout
    if getattr(scene, "visibility", None) is not None:  # an instance list with masks
        held = np.zeros(shape, bool) if held is None else held
        job.holdout = held.astype(np.float32).reshape(shape)
    job.picture = True  # its PNG is made when asked for (job_png)
    if "normal" in passes:
        job.extras["normal"] = np.asarray(normals, np.float32).reshape(*shape, 3)
    if not (depth or {"position", "object", "triangle"} & set(passes)):
        return  # nothing needs the camera rays' hits traced again (a film: nor made)
    if filtered:  # the film traced its own rays; these passes take the pixel centres'
        origins, directions, tmin, tmax = job.timed("camera", camera.rays)
    t, instance, triangle = job.timed("depth", lambda: seen_hits(views, origins, directions,
                                                                 tmin, tmax))
    hit = np.isfinite(t)
    t64 = np.where(hit, t, 0.0).astype(np.float64)[:, None]
    z = t64[:, 0] * (directions.astype(np.float64) * camera.forward).sum(axis=1)  # no BLAS
    if depth:
        job.depth = np.where(hit, z, BACKGROUND_DEPTH).astype(np.float32).reshape(shape)
    extras = {  # made only when asked for (JobRequest.passes)
        "position": lambda: np.where(hit[:, None], origins + t64 * directions,
                                     0.0).reshape(*shape, 3),
        "object": lambda: np.where(job.coverage.ravel() > 0, instance, -1).reshape(shape),
        # two 16-bit halves: float32 holds each exactly, whatever the mesh's size
        "triangle": lambda: np.where(job.coverage.ravel()[:, None] > 0,
                                     np.stack([triangle >> 16, triangle & 0xFFFF], axis=1),
                                     -1).reshape(*shape, 2),
    }
    job.extras.update({name: extras[name]().astype(np.float32) for name in passes
                       if name in extras})


def seen_hits(
    views: Views, origins: np.ndarray, directions: np.ndarray, tmin: np.ndarray,
    tmax: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per ray the closest seen hit's t (a holdout's too; inf on a miss), the instance
    hit (a single mesh's 0) and the triangle in its mesh: the same closest-hit query as
    AO's primary rays."""
    from scenesort import kernels

    hits = kernels.trace(views.camera, origins, directions, tmin, tmax)
    t, instance, triangle = hits.t, hits.instance, hits.triangle
    if views.holdout is not None:
        held = kernels.trace(views.holdout, origins, directions, tmin, tmax)
        nearer = held.t < t
        t, instance = np.where(nearer, held.t, t), np.where(nearer, held.instance, instance)
        triangle = np.where(nearer, held.triangle, triangle)
    return t, instance, triangle


def _reach(options: AoOptions) -> float:
    """How many pixels outside the image the render's camera rays start (its filter's)."""
    from scenesort.kernels.render.film import filter_reach

    return filter_reach(options.pixel_filter, options.filter_width) if options.filtered else 0.0


def _render_film(job: Job, views: Views, scene: Any, camera: Any, options: AoOptions) -> Any:
    """`kernels.render_film` of `camera` through the options' pixel filter with the scene's
    normals, occlusion rays through the views' occluders, reporting progress between its
    rounds; its `FilmResult`."""
    from scenesort import kernels

    def progress(fraction: float, phase: str) -> None:
        job.report(f"ao.{phase}", fraction)  # raises Stopped inside the engine's loop

    occluders = None if views.occluders is views.camera else views.occluders
    return kernels.render_film(views.camera, camera, options, occluders=occluders,
                               holdout=views.holdout, progress=progress, **shading(scene))


def _render_ao(
    job: Job,
    views: Views,
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

    occluders = None if views.occluders is views.camera else views.occluders
    result = kernels.render_ao(views.camera, origins, directions, options, tmin=tmin,
                               tmax=tmax, progress=progress, image_shape=shape,
                               occluders=occluders, holdout=views.holdout, **shading(scene))
    for name, ms in result.timings_ms.to_dict().items():
        job.add_timing(f"ao.{name}", float(ms))
    return result
