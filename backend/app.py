"""The HTTP API under /v1: thin FastAPI routes over wire.py, store.py and jobs.py.

Routes decode and validate (wire.py), look things up (store.py) and hand heavy work to
the device worker (jobs.py); none of them runs Warp on the event loop. Every client
mistake becomes a 4xx `ErrorBody` naming the parameter and the fix; anything else is a
logged 500 and the process carries on. docs/api.md describes the API for people.
"""

from __future__ import annotations

import importlib
import logging
import secrets
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import numpy as np
from fastapi import FastAPI, Path, Query, Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, StreamingResponse
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

from backend import __version__, jobs, wire
from backend.jobs import AoParams, DeviceWorker, JobManager, QueueFull
from backend.models import (
    OCTET,
    BvhInfo,
    BvhRequest,
    BvhStats,
    CacheUse,
    Health,
    JobRequest,
    JobStatus,
    SceneInfo,
    binary_body,
    error_responses,
)
from backend.store import Store
from backend.wire import ApiError

log = logging.getLogger("scenesort.app")

MAX_JOB_PIXELS = 4096 * 4096
SceneId = Annotated[
    str, Path(pattern=r"^[0-9a-f]{32}$", description="32 hex characters (see docs/api.md)")
]
JobId = Annotated[str, Path(pattern=r"^[0-9a-f]{16}$", description="16 hex characters")]


@dataclass(frozen=True)
class Settings:
    """What `scenesort serve` configures."""

    device: str = "cpu"
    token: str | None = None
    max_body_bytes: int = 512 * 2**20
    cache_bytes: int = 2048 * 2**20


# --- request helpers ----------------------------------------------------------------


async def read_body(request: Request, limit: int, expected: int) -> bytes:
    """The raw body, refused early (413) past `limit` and checked as octet-stream."""
    ctype = request.headers.get("content-type", OCTET).split(";")[0].strip().lower()
    if ctype != OCTET:
        raise ApiError(
            415,
            "Content-Type",
            f"body must be {OCTET}, got {ctype!r}",
            f"send the raw little-endian arrays with Content-Type: {OCTET}",
            "bad_content_type",
        )
    too_big = ApiError(
        413,
        "body",
        f"body exceeds the service's limit of {limit} bytes",
        "send a smaller scene/fewer rays, or start the service with a larger --max-body-mb",
        "body_too_large",
    )
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit():
        if int(declared) > limit:
            raise too_big
        if int(declared) != expected:  # fail before reading megabytes we would refuse
            wire.expect_body_length("the counts", int(declared), expected, "see docs/api.md")
    chunks: list[bytes] = []
    size = 0
    try:
        async for chunk in request.stream():
            chunks.append(chunk)
            size += len(chunk)
            if size > limit:
                raise too_big
    except ClientDisconnect:  # nobody will read the answer; log a 4xx, not a traceback
        raise ApiError(
            400,
            "body",
            "the client disconnected during the upload",
            "send the whole body",
            "client_disconnected",
        ) from None
    return b"".join(chunks)  # one copy at the end, not one per chunk


def _engine_error(parameter: str, exc: ValueError) -> ApiError:
    """An input the engine refused (its ValueErrors name the problem): the client's to fix."""
    return ApiError(
        422,
        parameter,
        f"the engine rejected the input: {exc}",
        "correct the value named in the message",
        "rejected_by_engine",
    )


def _queue_full(exc: QueueFull) -> ApiError:
    return ApiError(
        429,
        "request",
        f"the device queue is full ({exc})",
        "retry after the running work finishes",
        "busy",
    )


def _check_ao(params: AoParams) -> None:
    """Refuse what the engine would refuse, naming the query parameter."""
    max_spp = jobs.adaptive_max_spp()
    if params.target_error is not None and params.spp > max_spp:
        raise ApiError(
            422,
            "spp",
            f"with target_error, spp is the minimum per ray and must be <= {max_spp}, "
            f"got {params.spp}",
            f"lower spp to at most {max_spp}, or drop target_error for a fixed spp",
            "invalid_parameter",
        )


def _scene_or_404(store: Store, scene_id: str) -> wire.SceneArrays:
    scene = store.get(scene_id)
    if scene is None:
        raise ApiError(
            404,
            "scene_id",
            f"no scene {scene_id} on this service (or evicted)",
            "upload it with POST /v1/scenes first",
            "unknown_scene",
        )
    return scene


def _bvh_info(scene_id: str, method: str, leaf_size: int, bvh: Any, cached: bool) -> BvhInfo:
    stats = dict(bvh.stats)
    timings = {"total": float(stats["build_ms"])}
    timings.update({k: float(v) for k, v in stats.get("phase_ms", {}).items()})
    timings["compile"] = float(stats.get("compile_ms", 0.0))  # Warp's, not part of total
    fields = BvhStats.model_fields
    return BvhInfo(
        scene_id=scene_id,
        method=method,
        leaf_size=leaf_size,
        cached=cached,
        timings_ms=timings,
        stats=BvhStats(**{k: stats[k] for k in fields}),
    )


def _server_timing(timings: dict[str, float]) -> str:
    return ", ".join(f"{name};dur={ms:.3f}" for name, ms in timings.items())


# --- error handlers and middleware --------------------------------------------------

_FIXES = {
    "missing": "add {name}",
    "int_parsing": "send {name} as an integer",
    "int_from_float": "send {name} as an integer",
    "float_parsing": "send {name} as a finite number",
    "finite_number": "send {name} as a finite number",
    "greater_than": "use {name} > {gt}",
    "greater_than_equal": "use {name} >= {ge}",
    "less_than": "use {name} < {lt}",
    "less_than_equal": "use {name} <= {le}",
    "literal_error": "use one of {expected} for {name}",
    "extra_forbidden": "remove {name}; see /docs for the fields this route takes",
    "string_pattern_mismatch": "use an id as returned by the service ({pattern})",
    "json_invalid": "send a valid JSON object with Content-Type: application/json",
    "too_short": "give {name} the documented number of items",
    "too_long": "give {name} the documented number of items",
}


def _validation_error(_: Request, exc: RequestValidationError) -> JSONResponse:
    """FastAPI's 422 list -> one ErrorBody for the first problem, naming its parameter."""
    first = exc.errors()[0]
    kind = first.get("type", "")
    loc = [str(p) for p in first.get("loc", ())]
    if loc and loc[0] in ("query", "path", "header", "body"):
        loc = loc[1:]  # where it came from is implied by the name
    name = "body" if kind == "json_invalid" or not loc else ".".join(loc)
    ctx = {k: str(v) for k, v in (first.get("ctx") or {}).items()}
    template = _FIXES.get(kind, "see /docs for {name}'s type and range")
    fix = template.format_map({"name": name, **ctx})
    got = "" if kind in ("missing", "json_invalid") else f" (got {first.get('input')!r:.80})"
    message = f"{name}: {first.get('msg')}{got}"
    status = 400 if kind == "json_invalid" else 422
    body = ApiError(status, name, message, fix, "invalid_parameter")
    return JSONResponse(body.to_json(), status_code=status)


def _api_error(_: Request, exc: ApiError) -> JSONResponse:
    return JSONResponse(exc.to_json(), status_code=exc.status)


def _http_error(_: Request, exc: StarletteHTTPException) -> JSONResponse:
    parameter = {404: "path", 405: "method"}.get(exc.status_code, "request")
    fix = "see /docs for the routes and methods this service has"
    body = ApiError(exc.status_code, parameter, str(exc.detail), fix, "http_error")
    return JSONResponse(body.to_json(), status_code=exc.status_code, headers=exc.headers)


def _internal_error(request: Request, exc: Exception) -> JSONResponse:
    log.error("internal error on %s %s", request.method, request.url.path, exc_info=exc)
    fix = "this is a service bug; the log has the traceback"
    body = ApiError(500, "request", f"internal error: {type(exc).__name__}", fix, "internal_error")
    return JSONResponse(body.to_json(), status_code=500)


class AccessMiddleware:
    """Pure ASGI: bearer-token check and one log line per request with its duration.

    Pure ASGI (not BaseHTTPMiddleware) so that streamed responses and client
    disconnects pass straight through.
    """

    OPEN_PATHS = frozenset({"/v1/health", "/docs", "/openapi.json"})

    def __init__(self, app: Any, token: str | None) -> None:
        self.app = app
        self.expected = f"Bearer {token}".encode() if token else None

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = [0]

        async def send_logged(message: dict) -> None:
            if message["type"] == "http.response.start":
                status[0] = message["status"]
            await send(message)

        try:
            if (
                self.expected
                and scope["path"] not in self.OPEN_PATHS
                and not self._authorized(scope)
            ):
                error = ApiError(
                    401,
                    "Authorization",
                    "missing or wrong bearer token",
                    "send 'Authorization: Bearer <token given to serve --token>'",
                    "unauthorized",
                )
                response = JSONResponse(error.to_json(), status_code=401)
                await response(scope, receive, send_logged)
            else:
                await self.app(scope, receive, send_logged)
        except BaseException:
            status[0] = status[0] or 500  # ServerErrorMiddleware, outside us, answers 500
            raise
        finally:
            query = scope.get("query_string", b"").decode("latin-1")
            path = scope["path"] + (f"?{query}" if query else "")
            ms = 1000.0 * (time.perf_counter() - start)
            log.info("%s %s -> %s in %.1f ms", scope["method"], path, status[0] or "-", ms)

    def _authorized(self, scope: dict) -> bool:
        for key, value in scope.get("headers", []):
            if key == b"authorization":
                return secrets.compare_digest(value, self.expected or b"")
        return False


# --- the application ----------------------------------------------------------------


def create_app(settings: Settings | None = None) -> FastAPI:
    """Build the service: one store, one device worker, one job manager."""
    settings = settings or Settings()
    store = Store(settings.cache_bytes)
    worker = DeviceWorker(settings.device)
    manager = JobManager(worker)

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        # Import the engine and load its kernels before the first request, not during it.
        await run_in_threadpool(importlib.import_module, "kernels")
        worker.submit(lambda: jobs.warm_up(settings.device))
        yield
        await run_in_threadpool(worker.stop)  # let the running task end (bounded wait)

    app = FastAPI(
        title="scenesort",
        version=__version__,
        description="BVH builds and ambient-occlusion renders over loopback. See docs/api.md.",
        lifespan=lifespan,
    )
    app.state.settings, app.state.store, app.state.worker = settings, store, worker
    app.state.jobs = manager
    app.add_exception_handler(ApiError, _api_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(Exception, _internal_error)
    app.add_middleware(AccessMiddleware, token=settings.token)
    common = error_responses(400, 401, 422, 429)

    @app.get("/v1/health", response_model=Health)
    async def health() -> Health:
        """Liveness, versions, the device and the cache's use of its byte budget."""
        import warp

        return Health(
            version=__version__,
            warp_version=warp.config.version,
            device=settings.device,
            cache=CacheUse(**store.usage()),
            queued=worker.queued,
            active_jobs=manager.active(),
        )

    @app.post(
        "/v1/scenes",
        response_model=SceneInfo,
        status_code=201,
        responses={
            200: {"model": SceneInfo, "description": "already known"},
            **error_responses(400, 401, 413, 415, 422),
        },
        openapi_extra=binary_body(
            "V*3 little-endian float32 positions, then T*3 little-endian int32 indices "
            "(0-based), no header or padding: exactly 12*V + 12*T bytes."
        ),
    )
    async def upload_scene(
        request: Request,
        response: Response,
        vertices: Annotated[int, Query(ge=1, le=wire.MAX_INDEXABLE_VERTICES)],
        triangles: Annotated[int, Query(ge=1, le=2**31 - 1)],
    ) -> SceneInfo:
        """Upload a triangle mesh; its content hash is its id (201 new, 200 known)."""
        t0 = time.perf_counter()
        expected = 12 * (vertices + triangles)
        body = await read_body(request, settings.max_body_bytes, expected)
        t1 = time.perf_counter()
        scene_id = await run_in_threadpool(wire.scene_hash, vertices, triangles, body)
        t2 = time.perf_counter()
        scene = store.get(scene_id)
        if scene is None:  # only new scenes pay for decoding and validation
            scene = await run_in_threadpool(wire.decode_scene, body, vertices, triangles, scene_id)
            if scene.nbytes > settings.cache_bytes:
                raise ApiError(
                    413,
                    "body",
                    f"the scene needs {scene.nbytes} bytes of cache, more than the "
                    f"whole cache ({settings.cache_bytes})",
                    "start the service with a larger --cache-mb",
                    "scene_too_large",
                )
            store.put(scene_id, scene, scene.nbytes)
        else:
            response.status_code = 200
        timings = {"read": t1 - t0, "hash": t2 - t1, "decode": time.perf_counter() - t2}
        timings["total"] = time.perf_counter() - t0
        response.headers["Server-Timing"] = _server_timing({k: 1e3 * v for k, v in timings.items()})
        return SceneInfo(
            scene_id=scene_id,
            vertices=vertices,
            triangles=triangles,
            bounds=scene.bounds,
            degenerate=scene.degenerate,
            bytes=scene.nbytes,
        )

    @app.head("/v1/scenes/{scene_id}", responses={404: {"description": "unknown scene"}})
    async def has_scene(scene_id: SceneId) -> Response:
        """200 if the service holds this scene, else 404: clients skip unchanged uploads."""
        return Response(status_code=200 if store.get(scene_id) is not None else 404)

    @app.get("/v1/scenes/{scene_id}", response_model=SceneInfo, responses=error_responses(404, 422))
    async def scene_info(scene_id: SceneId) -> SceneInfo:
        """What the service knows about a scene."""
        scene = _scene_or_404(store, scene_id)
        return SceneInfo(
            scene_id=scene_id,
            vertices=len(scene.vertices),
            triangles=len(scene.indices),
            bounds=scene.bounds,
            degenerate=scene.degenerate,
            bytes=scene.nbytes,
        )

    @app.post("/v1/scenes/{scene_id}/bvh", response_model=BvhInfo,
              responses=error_responses(404, *common))
    async def build_bvh(scene_id: SceneId, spec: BvhRequest, response: Response) -> BvhInfo:
        """Build (or reuse) the scene's BVH with these parameters; per-phase timings.

        A Server-Timing header gives the wait in the device queue and the build's wall
        time in the service (including the statistics the engine computes after it)."""
        t0 = time.perf_counter()
        scene = _scene_or_404(store, scene_id)
        started: list[float] = []

        def work() -> tuple[Any, bool]:
            started.append(time.perf_counter())
            return jobs.get_or_build_bvh(store, scene, spec.method, spec.leaf_size, settings.device)

        try:
            bvh, cached = await worker.run(work)
        except QueueFull as exc:
            raise _queue_full(exc) from None
        except ValueError as exc:
            raise _engine_error("scene", exc) from None
        t1 = time.perf_counter()
        timings = {"queue": started[0] - t0, "build": t1 - started[0], "total": t1 - t0}
        response.headers["Server-Timing"] = _server_timing({k: 1e3 * v for k, v in timings.items()})
        return _bvh_info(scene_id, spec.method, spec.leaf_size, bvh, cached)

    @app.post(
        "/v1/scenes/{scene_id}/ao",
        response_class=Response,
        responses={
            200: {
                "content": {OCTET: {"schema": {"type": "string", "format": "binary"}}},
                "description": "R little-endian float32 AO values, one per ray, in order; "
                "a Server-Timing header lists the phases in ms.",
            },
            **error_responses(404, 413, 415, *common),
        },
        openapi_extra=binary_body(
            "R*6 little-endian float32: origin xyz then direction xyz per ray (directions "
            "need not be unit length, must be nonzero): exactly 24*R bytes."
        ),
    )
    async def ambient_occlusion(
        request: Request,
        scene_id: SceneId,
        rays: Annotated[int, Query(ge=1, le=2**27)],
        spp: Annotated[int, Query(ge=1, le=4096)] = 16,
        distance: Annotated[float | None, Query(gt=0, allow_inf_nan=False)] = None,
        seed: Annotated[int, Query(ge=0, le=2**31 - 1)] = 0,
        target_error: Annotated[float | None, Query(gt=0, lt=1, allow_inf_nan=False)] = None,
        engine: Literal["bvh", "dacrt"] = "bvh",
        method: Literal["sah", "median"] | None = None,
        leaf_size: Annotated[int | None, Query(ge=1, le=64)] = None,
    ) -> Response:
        """AO per ray, identical to `kernels.ambient_occlusion` for the same inputs.

        Uses the BVH built with `method`/`leaf_size` when given, else the scene's most
        recently used BVH, else builds one with the defaults (sah, 8).
        """
        t0 = time.perf_counter()
        scene = _scene_or_404(store, scene_id)
        params = AoParams(
            spp=spp, distance=distance, seed=seed, target_error=target_error, engine=engine
        )
        _check_ao(params)
        body = await read_body(request, settings.max_body_bytes, 24 * rays)
        t1 = time.perf_counter()
        origins, directions = await run_in_threadpool(wire.decode_rays, body, rays)
        t2 = time.perf_counter()
        timings: dict[str, float] = {}

        def work() -> np.ndarray:
            # Runs on the worker: pick or build the BVH there, never on the event loop.
            w0 = time.perf_counter()
            bvh = jobs.bvh_for_ao(store, scene, method, leaf_size, settings.device)
            w1 = time.perf_counter()
            ao, engine_ms = jobs.ambient_occlusion(bvh, origins, directions, params)
            timings.update(bvh=1000 * (w1 - w0), ao=1000 * (time.perf_counter() - w1))
            timings.update({f"ao.{k}": v for k, v in engine_ms.items() if k != "total"})
            return ao

        try:
            ao = await worker.run(work)
        except QueueFull as exc:
            raise _queue_full(exc) from None
        except ValueError as exc:
            raise _engine_error("rays", exc) from None
        payload = await run_in_threadpool(wire.encode_f32, ao)
        total = 1000 * (time.perf_counter() - t0)
        all_timings = {
            "read": 1000 * (t1 - t0),
            "decode": 1000 * (t2 - t1),
            **timings,
            "total": total,
        }
        return Response(
            payload, media_type=OCTET, headers={"Server-Timing": _server_timing(all_timings)}
        )

    @app.post(
        "/v1/jobs", response_model=JobStatus, status_code=202,
        responses=error_responses(404, *common),
    )
    async def create_job(request: JobRequest) -> JobStatus:
        """Queue an AO render of `camera`'s pixels; poll it, stream its events, fetch it."""
        from kernels import Camera

        try:
            camera = Camera.from_dict(request.camera.model_dump())
        except ValueError as exc:
            raise ApiError(
                422,
                "camera",
                str(exc),
                "correct the camera field named in the message (see kernels/camera.py)",
                "invalid_camera",
            ) from None
        if camera.width * camera.height > MAX_JOB_PIXELS:
            raise ApiError(
                422,
                "camera.width",
                f"{camera.width}x{camera.height} is more than {MAX_JOB_PIXELS} pixels",
                "render a smaller image or tiles",
                "too_many_pixels",
            )
        scene = _scene_or_404(store, request.scene_id)
        params = AoParams(
            spp=request.spp,
            distance=request.distance,
            seed=request.seed,
            target_error=request.target_error,
            engine=request.engine,
        )
        _check_ao(params)

        def work(job: jobs.Job) -> None:
            jobs.render_camera(
                job,
                store,
                scene,
                camera,
                params,
                request.method,
                request.leaf_size,
                settings.device,
            )

        try:
            job = manager.create(request.scene_id, camera.width, camera.height, work)
        except QueueFull as exc:
            raise _queue_full(exc) from None
        return JobStatus(**job.snapshot())

    def job_or_404(job_id: str) -> jobs.Job:
        job = manager.get(job_id)
        if job is None:
            raise ApiError(
                404,
                "job_id",
                f"no job {job_id} (unknown, or finished long ago)",
                "create a job with POST /v1/jobs",
                "unknown_job",
            )
        return job

    @app.get("/v1/jobs/{job_id}", response_model=JobStatus, responses=error_responses(404, 422))
    async def job_status(job_id: JobId) -> JobStatus:
        """State, phase, progress (0..1) and per-phase timings of a job."""
        return JobStatus(**job_or_404(job_id).snapshot())

    @app.delete("/v1/jobs/{job_id}", response_model=JobStatus, responses=error_responses(404, 422))
    async def cancel_job(job_id: JobId) -> JobStatus:
        """Cancel a job: a queued one never starts, a running one stops at its next step."""
        manager.cancel(job_id)
        return JobStatus(**job_or_404(job_id).snapshot())

    @app.get(
        "/v1/jobs/{job_id}/result",
        response_class=Response,
        responses={
            200: {
                "content": {
                    OCTET: {"schema": {"type": "string", "format": "binary"}},
                    "image/png": {"schema": {"type": "string", "format": "binary"}},
                },
                "description": "format=f32: height*width little-endian float32, row 0 at "
                "the top; format=png: 8-bit grayscale PNG. X-Width/X-Height headers.",
            },
            **error_responses(404, 409, 422),
        },
    )
    async def job_result(job_id: JobId, format: Literal["f32", "png"] = "f32") -> Response:
        """The finished image; 409 while the job is not done."""
        job = job_or_404(job_id)
        if job.state != "done" or job.ao is None or job.png is None:
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
            "Server-Timing": _server_timing(job.snapshot()["timings_ms"]),
        }
        if format == "png":
            return Response(job.png, media_type="image/png", headers=headers)
        payload = await run_in_threadpool(wire.encode_f32, job.ao)
        return Response(payload, media_type=OCTET, headers=headers)

    @app.get(
        "/v1/jobs/{job_id}/events",
        response_class=StreamingResponse,
        responses={
            200: {
                "content": {"text/event-stream": {"schema": {"type": "string"}}},
                "description": "server-sent events: `progress` on each change (data "
                "is a JobStatus), then one `end`",
            },
            **error_responses(404, 422),
        },
    )
    async def job_events(job_id: JobId, request: Request) -> StreamingResponse:
        """Progress as server-sent events until the job ends or the client leaves."""
        job = job_or_404(job_id)
        return StreamingResponse(
            jobs.job_events(job, request.is_disconnected),
            media_type="text/event-stream",
            headers={"Cache-Control": "no-cache"},
        )

    return app
