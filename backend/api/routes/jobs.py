"""Renders as jobs: POST /v1/jobs queues a camera's, POST /v1/scenes/{scene_id}/surface-jobs
one of explicit surface points (a bake's texels); GET polls a job, DELETE cancels it,
/result fetches its image (AO, coverage, depth or PNG) and /events streams its progress as
server-sent events."""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable
from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request, Response
from fastapi.responses import StreamingResponse
from scenesort.backend.api import errors, limits
from scenesort.backend.api.openapi import COMMON_ERRORS
from scenesort.backend.api.params import JobId, SceneId
from scenesort.backend.api.requests import read_body, server_timing
from scenesort.backend.api.service import Service, Shared
from scenesort.backend.render.camera_render import job_camera, job_png, render_camera
from scenesort.backend.render.surface_render import render_surface
from scenesort.backend.wire import binary as wire
from scenesort.backend.wire.models import (
    OCTET,
    JobRequest,
    JobStatus,
    SurfaceJobQuery,
    binary_body,
    error_responses,
)
from scenesort.backend.wire.problems import ApiError, busy
from scenesort.backend.work.jobs import Job, until_final
from scenesort.backend.work.jobs import job_events as progress_events
from scenesort.backend.work.worker import QueueFull
from starlette.background import BackgroundTask
from starlette.concurrency import run_in_threadpool

router = APIRouter()
MAX_WAIT_S = 10.0  # a long poll holds a connection: short enough to see a cancelled client


@router.post(
    "/v1/jobs", response_model=JobStatus, status_code=202,
    responses=error_responses(404, *COMMON_ERRORS),
)
async def create_job(request: JobRequest, response: Response, service: Shared) -> JobStatus:
    """Queue an AO render of `camera`'s pixels; poll it, stream its events, fetch it."""
    try:
        camera = job_camera(request)
    except ValueError as exc:
        raise ApiError(
            422,
            "camera",
            str(exc),
            "correct the camera field named in the message (see kernels/render/camera.py)",
            "invalid_camera",
        ) from None
    limits.check_pixels(camera.width, camera.height)
    options = request.options()
    limits.check_denoiser(options)
    limits.check_work(service.settings.max_work, camera.width * camera.height,
                      "camera.width x camera.height", options)
    scene = service.scene(request.scene_id)
    limits.check_engine(scene, options)

    def work(job: Job) -> None:
        render_camera(job, service.store, scene, camera, options, request.method,
                      request.leaf_size, service.settings.device, passes=request.passes,
                      depth=request.depth)

    return _queue(service, response, request.scene_id, camera.width, camera.height, work)


@router.post(
    "/v1/scenes/{scene_id}/surface-jobs", response_model=JobStatus, status_code=202,
    responses=error_responses(404, *COMMON_ERRORS),
    openapi_extra=binary_body(wire.SURFACE_POINTS_LAYOUT + ": exactly 12*P bytes."),
)
async def create_surface_job(
    request: Request, scene_id: SceneId, query: Annotated[SurfaceJobQuery, Query()],
    response: Response, service: Shared,
) -> JobStatus:
    """Queue AO at explicit points of a flattened scene's triangles, seen from the side
    each triangle's winding faces (a bake's texels; kernels.surface_ao): the job's image
    is 1 x P, its coverage 0 for points on triangles without area."""
    options = query.options()
    if options.engine != "bvh":
        raise ApiError(422, "engine", "surface jobs trace with the BVH engine",
                       "leave engine unset or set it to bvh", "invalid_parameter")
    limits.check_work(service.settings.max_work, query.points, "points", options)
    scene = service.scene(scene_id)
    if isinstance(scene, wire.InstanceScene):
        raise ApiError(422, "scene_id", "surface points index a flattened scene's triangles; "
                       "this is an instance list", "upload the flattened scene with POST "
                       "/v1/scenes and use its id", "invalid_parameter")  # fmt: skip
    body = await read_body(request, 12 * query.points)
    points = await run_in_threadpool(wire.decode_surface_points, body, query.points)
    del body

    def work(job: Job) -> None:
        render_surface(job, service.store, scene, points, options, query.method,
                       query.leaf_size, service.settings.device)

    return _queue(service, response, scene_id, query.points, 1, work)


def _queue(service: Service, response: Response, scene_id: str, width: int, height: int,
           work: Callable[[Job], None]) -> JobStatus:
    try:
        job = service.jobs.create(scene_id, width, height, work)
    except QueueFull as exc:
        raise errors.queue_full(exc) from None
    response.headers["Location"] = f"/v1/jobs/{job.job_id}"
    return JobStatus(**job.snapshot())


@router.get("/v1/jobs/{job_id}", response_model=JobStatus, responses=error_responses(404, 422))
async def job_status(
    job_id: JobId, service: Shared,
    wait: Annotated[float, Query(ge=0.0, le=MAX_WAIT_S, description=(
        "seconds to wait for the job to end before answering (a long poll)"))] = 0.0,
) -> JobStatus:
    """State, phase, progress (0..1) and per-phase timings of a job; with `wait`, as soon
    as the job ends or after `wait` seconds."""
    job = service.job(job_id)
    if wait > 0.0:
        await until_final(job, wait)
    return JobStatus(**job.snapshot())


@router.delete("/v1/jobs/{job_id}", response_model=JobStatus,
               responses=error_responses(404, 422))
async def cancel_job(job_id: JobId, service: Shared) -> JobStatus:
    """Cancel a job: a queued one never starts (and frees its place in the queue), a
    running one stops at its next step."""
    job = service.job(job_id)
    service.jobs.cancel(job_id)
    return JobStatus(**job.snapshot())


@router.get(
    "/v1/jobs/{job_id}/result",
    response_class=Response,
    responses={
        200: {
            "content": {
                OCTET: {"schema": {"type": "string", "format": "binary"}},
                "image/png": {"schema": {"type": "string", "format": "binary"}},
            },
            "description": "format=f32: height*width little-endian float32 AO, row 0 "
            "at the top (depth only when the job asked for it, as by default); "
            "format=coverage: the same layout, 1.0 where the camera ray "
            "hit and 0.0 where it missed; format=depth: the same layout, the hit's "
            "camera-space depth (Cycles' Z pass), 1e10 where it missed; format=holdout: "
            "the same layout, 1.0 where the camera sees a holdout instance (alpha 0, AO 0) "
            "and 0.0 elsewhere, through a pixel filter the fraction of the pixel's samples "
            "that see one (a scene sent with visibility masks); format=normal and "
            "format=position: height*width*3 float32 (x, y, z per pixel, 0 on background), "
            "format=object: height*width float32 instance indices (-1 on background), "
            "format=triangle: height*width*2 float32, the triangle hit in its instance's "
            "mesh as index // 65536 and index % 65536 (-1, -1 on background), "
            "each when the job's passes asked for it; format=png: "
            "8-bit grayscale PNG of the AO. X-Width/X-Height headers.",
        },
        **error_responses(404, 409, 422),
    },
)
async def job_result(
    job_id: JobId, service: Shared,
    format: Literal["f32", "coverage", "depth", "holdout", "normal", "position", "object",
                    "triangle", "png"] = "f32",
) -> Response:
    """The finished image (AO, coverage, depth, holdout or an extra pass); 409 while the
    job is not done or did not make it."""
    job = service.job(job_id)
    # One read: the manager may forget the job meanwhile.
    layer = {"f32": job.ao, "coverage": job.coverage, "depth": job.depth,
             "holdout": job.holdout}.get(format, job.extras.get(format))
    if format == "png":  # encoded on first request, off the event loop
        layer = await run_in_threadpool(job_png, job)
    if job.state == "done" and layer is None:
        raise ApiError(
            409, "format", f"job {job_id} made no {format} image",
            "ask for it in the job's passes (holdout: send the instance list with "
            "visibility masks), then render again", "not_made",
        )
    if job.state != "done" or layer is None:
        detail = f" ({job.error})" if job.error else ""
        raise ApiError(
            409,
            "job_id",
            f"job {job_id} is {job.state}{detail}, not done",
            "poll GET /v1/jobs/{job_id} until state is done",
            "not_done",
        )
    headers = {
        "X-Width": str(job.width),
        "X-Height": str(job.height),
        "Server-Timing": server_timing(job.snapshot()["timings_ms"]),
    }
    if format == "png":
        return Response(layer, media_type="image/png", headers=headers)
    payload = await run_in_threadpool(wire.encode_f32, layer)
    return Response(payload, media_type=OCTET, headers=headers)


@router.get(
    "/v1/jobs/{job_id}/events",
    response_class=StreamingResponse,
    responses={
        200: {
            "content": {"text/event-stream": {"schema": {"type": "string"}}},
            "description": "server-sent events: `progress` on each change (data "
            "is a JobStatus), then one `end`",
        },
        **error_responses(404, 422, 429),
    },
)
async def job_events(job_id: JobId, request: Request, service: Shared) -> StreamingResponse:
    """Progress as server-sent events until the job ends or the client leaves."""
    job = service.job(job_id)
    if job.streams >= service.settings.max_streams_per_job:
        raise busy(
            "job_id", f"{job.streams} event streams are already open on job {job_id}",
            "share one stream, or poll GET /v1/jobs/{job_id}", 2, status=429,
        )
    job.streams += 1
    released = [False]

    def release() -> None:  # once, from whichever of the two ends runs
        if not released[0]:
            released[0] = True
            job.streams -= 1

    async def events() -> AsyncIterator[str]:
        try:
            async for event in progress_events(job, request.is_disconnected):
                yield event
        finally:
            release()

    return StreamingResponse(
        events(),
        media_type="text/event-stream",
        headers={"Cache-Control": "no-cache"},
        background=BackgroundTask(release),
    )
