"""The HTTP API under /v1: thin FastAPI routes over wire.py, store.py and jobs.py.

Routes decode and validate (wire.py), look things up (store.py) and hand heavy work to
the device worker (jobs.py); none of them runs Warp on the event loop. security.py's
`Guard` checks Host, Origin, the token and the bodies before any route runs. Every
client mistake becomes a 4xx problem document (problems.py) naming the parameter and the
fix; running out of memory is a 507/503; anything else is a logged 500 and the process
carries on. docs/api.md describes the API for people, docs/security.md its defences.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from typing import Annotated, Any, Literal

import numpy as np
from fastapi import FastAPI, Path, Query, Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, StreamingResponse
from scenesort.backend import __version__
from scenesort.backend.api.security import AUTHORIZED, Guard, Policy, escape
from scenesort.backend.render import ao as service_ao
from scenesort.backend.render import bvhs, camera_render, engine
from scenesort.backend.render.ao import AoParams
from scenesort.backend.wire import binary as wire
from scenesort.backend.wire.models import (
    MAX_PIXEL_ERROR_DOC,
    OCTET,
    TARGET_ERROR_DOC,
    BvhInfo,
    BvhRequest,
    BvhStats,
    CacheUse,
    Health,
    InstanceSceneInfo,
    JobRequest,
    JobStatus,
    SceneInfo,
    binary_body,
    error_responses,
)
from scenesort.backend.wire.problems import ApiError, busy
from scenesort.backend.work import jobs
from scenesort.backend.work.jobs import TOO_LARGE, JobManager
from scenesort.backend.work.stop import Stopped, StopSignal
from scenesort.backend.work.store import Store
from scenesort.backend.work.worker import DeviceWorker, QueueFull
from starlette.background import BackgroundTask
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

BEARER = "bearer"  # the OpenAPI security scheme of the token
log = logging.getLogger("scenesort.app")

MAX_JOB_PIXELS = 4096 * 4096
DISCONNECT_POLL_S = 0.25  # how often a waiting request looks for its client having gone
SHUTDOWN = "the service is shutting down"
SceneId = Annotated[
    str, Path(pattern=r"^[0-9a-f]{32}$", description="32 hex characters (see docs/api.md)")
]
JobId = Annotated[str, Path(pattern=r"^[0-9a-f]{16}$", description="16 hex characters")]
# The counts and flags of a scene or mesh body (query parameters).
Vertices = Annotated[int, Query(ge=1, le=wire.MAX_INDEXABLE_VERTICES)]
Triangles = Annotated[int, Query(ge=1, le=2**31 - 1)]
Normals = Annotated[bool, Query(description="the body ends with T*9 float32 corner normals "
                                "(smooth shading)")]
Offsets = Annotated[bool, Query(description="after the normals, T float32 shadow terminator "
                                "offsets")]


@dataclass(frozen=True)
class Settings:
    """What `scenesort serve` configures."""

    device: str = "cpu"
    cache_bytes: int = 2048 * 2**20
    result_bytes: int = 512 * 2**20  # finished jobs' images
    max_work: int = 2**32  # ray casts per request or job (rays x spp, pixels x spp)
    max_seconds: float = 1800.0  # deadline of a request's or a job's work
    max_streams_per_job: int = 4
    policy: Policy = field(default_factory=Policy)  # Host, Origin, token, bodies


# --- request helpers ----------------------------------------------------------------


async def read_body(request: Request, expected: int) -> bytes:
    """The raw body; Guard has checked its type and meters its size and pace."""
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) != expected:
        # fail before reading megabytes we would refuse
        wire.expect_body_length("the counts", int(declared), expected, "see docs/api.md")
    chunks: list[bytes] = []
    try:
        async for chunk in request.stream():
            chunks.append(chunk)
    except ClientDisconnect:  # nobody will read the answer; log a 4xx, not a traceback
        raise _gone() from None
    return b"".join(chunks)  # one copy at the end, not one per chunk


def _gone() -> ApiError:
    return ApiError(
        400, "body", "the client disconnected", "keep the connection open for the answer",
        "client_disconnected",
    )


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
    return busy(
        "request", f"the device queue is full ({exc})",
        "retry after the Retry-After seconds, when the running work has moved on",
        status=429,
    )


def _out_of_memory(exc: BaseException) -> ApiError:
    """MemoryError (507) or a Warp RuntimeError, which is how its allocations fail (503)."""
    if isinstance(exc, MemoryError):
        return ApiError(507, "body", TOO_LARGE, "send a smaller scene or fewer rays",
                        "too_large")
    return busy("body", f"{TOO_LARGE} (the engine said: {exc})",
                "send a smaller scene or fewer rays, or retry when other work has finished",
                code="engine_unavailable")


def _shutting_down() -> ApiError:
    return busy("request", SHUTDOWN, "retry when the service runs again", 5)


def _stopped(exc: Stopped, signal: StopSignal) -> ApiError:
    if not signal.stopped:  # the deadline
        return ApiError(
            422, "rays, spp", f"the work stopped {exc}",
            "send fewer rays or samples, or start the service with a larger --max-seconds",
            "deadline",
        )
    if signal.reason == SHUTDOWN:
        return _shutting_down()
    return _gone()


def _log_stop(done: asyncio.Future) -> None:
    """Say when work ended early (also after its client left: nobody else would know)."""
    if not done.cancelled() and isinstance(done.exception(), Stopped):
        log.info("work stopped early: %s", done.exception())


async def run_on_worker(
    request: Request, signal: StopSignal, parameter: str, fn: Callable[[], Any]
) -> Any:
    """`fn` on the device worker; its engine failures as problems. A client that hangs up
    stops the work (queued: never starts; running: at the engine's next round)."""
    worker, live = request.app.state.worker, request.app.state.live
    live.add(signal)
    try:
        future = worker.submit(fn)
        waiting = asyncio.wrap_future(future)
        waiting.add_done_callback(_log_stop)
        while not waiting.done():
            await asyncio.wait({waiting}, timeout=DISCONNECT_POLL_S)
            if waiting.done():
                break
            if await request.is_disconnected():
                signal.stop("the client disconnected")
                future.cancel()
                raise _gone()
            if signal.stopped and future.cancel():  # stopped while queued: never starts
                raise Stopped(signal.reason)
        if waiting.cancelled():  # the worker dropped it: the service is stopping
            raise _shutting_down()
        return waiting.result()
    except QueueFull as exc:
        raise _queue_full(exc) from None
    except ValueError as exc:
        raise _engine_error(parameter, exc) from None
    except Stopped as exc:
        raise _stopped(exc, signal) from None
    except (MemoryError, RuntimeError) as exc:
        raise _out_of_memory(exc) from None
    finally:
        live.discard(signal)


def _check_work(settings: Settings, count: int, count_name: str, params: AoParams) -> None:
    """Refuse a request whose ray casts (count x samples per ray) exceed --max-work."""
    per_ray = engine.adaptive_max_spp() if params.adaptive else params.spp
    spp_name = "the adaptive cap of spp" if params.adaptive else "spp"
    work = count * per_ray
    if work > settings.max_work:
        raise ApiError(
            422, f"{count_name}, spp",
            f"{count_name} x {spp_name} = {count} x {per_ray} = {work} ray casts, over this "
            f"service's budget of {settings.max_work} (serve --max-work)",
            f"lower {count_name} or spp so that their product is at most {settings.max_work}"
            ", split the work into several requests, or start the service with a larger "
            "--max-work",
            "over_budget",
        )


def _check_ao(params: AoParams) -> None:
    """Refuse what the engine would refuse, naming the query parameter."""
    max_spp = engine.adaptive_max_spp()
    if params.adaptive and params.spp > max_spp:
        raise ApiError(
            422,
            "spp",
            f"with target_error or max_pixel_error, spp is the minimum per ray and must be "
            f"<= {max_spp}, got {params.spp}",
            f"lower spp to at most {max_spp}, or drop target_error and max_pixel_error for "
            "a fixed spp",
            "invalid_parameter",
        )
    problem = engine.denoiser_problem() if params.denoise else None
    if problem is not None:
        raise ApiError(
            422, "denoise", f"this service cannot denoise: {problem}",
            f"install the extra where the service runs ({engine.denoise_extra()}) and "
            "restart it, or send denoise=false",
            "denoiser_missing",
        )


def _check_engine(scene: Any, params: AoParams) -> None:
    """DACRT traces one flat triangle list: instance lists are for the BVH engine."""
    if params.engine == "dacrt" and isinstance(scene, wire.InstanceScene):
        raise ApiError(
            422, "engine", "engine dacrt traces single-mesh scenes; this is an instance list",
            "use engine bvh for instance lists, or upload the flattened scene with "
            "POST /v1/scenes for dacrt",
            "invalid_parameter",
        )


def _mesh_or_none(store: Store, mesh_id: str) -> wire.SceneArrays | None:
    found = store.get(mesh_id)
    return found if isinstance(found, wire.SceneArrays) else None


def _scene_or_404(store: Store, scene_id: str) -> wire.SceneArrays | wire.InstanceScene:
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
    """FastAPI's 422 list -> one problem for the first error, naming its parameter."""
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
    return ApiError(status, name, message, fix, "invalid_parameter").response()


def _api_error(_: Request, exc: ApiError) -> JSONResponse:
    return exc.response()


def _http_error(_: Request, exc: StarletteHTTPException) -> JSONResponse:
    parameter = {404: "path", 405: "method"}.get(exc.status_code, "request")
    fix = "see /docs for the routes and methods this service has"
    error = ApiError(exc.status_code, parameter, str(exc.detail), fix, "http_error",
                     dict(exc.headers or {}))
    return error.response()


def _memory_error(_: Request, exc: MemoryError) -> JSONResponse:
    """Out of memory anywhere in a request (reading, hashing, decoding): 507, not 500."""
    return _out_of_memory(exc).response()


def _internal_error(request: Request, exc: Exception) -> JSONResponse:
    log.error("internal error on %s %s", request.method, escape(request.url.path), exc_info=exc)
    fix = "this is a service bug; the log has the traceback"
    return ApiError(
        500, "request", f"internal error: {type(exc).__name__}", fix, "internal_error"
    ).response()


def _etag(scene_id: str) -> str:
    return f'"{scene_id}"'


def _not_modified(request: Request, scene_id: str) -> bool:
    """Whether If-None-Match names this scene's ETag (or is *)."""
    header = request.headers.get("if-none-match")
    if header is None:
        return False
    tags = {t.strip().removeprefix("W/") for t in header.split(",")}
    return "*" in tags or _etag(scene_id) in tags


# --- the application ----------------------------------------------------------------


def create_app(settings: Settings | None = None) -> FastAPI:
    """Build the service: one store, one device worker, one job manager."""
    settings = settings or Settings()
    store = Store(settings.cache_bytes)
    worker = DeviceWorker(settings.device)
    manager = JobManager(
        worker, result_bytes=settings.result_bytes, max_seconds=settings.max_seconds
    )

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        # Import the engine and load its kernels before the first request, not during it.
        await run_in_threadpool(engine.load)
        worker.submit(lambda: engine.warm_up(settings.device))
        yield
        stop_work(app)
        await run_in_threadpool(worker.stop, 3.0)  # the running task ends at its next round

    app = FastAPI(
        title="scenesort",
        version=__version__,
        description="BVH builds and ambient-occlusion renders over loopback. See docs/api.md.",
        lifespan=lifespan,
    )
    app.state.settings, app.state.store, app.state.worker = settings, store, worker
    app.state.jobs, app.state.live = manager, set()
    app.add_exception_handler(ApiError, _api_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(MemoryError, _memory_error)
    app.add_exception_handler(Exception, _internal_error)
    app.add_middleware(Guard, policy=settings.policy)
    common = error_responses(400, 401, 403, 408, 413, 415, 422, 429, 503, 507)

    def deadline() -> StopSignal:
        return StopSignal(deadline=time.monotonic() + settings.max_seconds)

    @app.get("/v1/health", response_model=Health, response_model_exclude_none=True,
             openapi_extra={"security": [{}, {BEARER: []}]})  # the token is optional here
    async def health(request: Request) -> Health:
        """Liveness and versions; with the token also the device, cache and queue."""
        if not request.scope.get(AUTHORIZED):
            return Health(version=__version__, warp_version=engine.warp_version())
        return Health(
            version=__version__,
            warp_version=engine.warp_version(),
            device=settings.device,
            devices=engine.devices(),
            cache=CacheUse(**store.usage()),
            queued=worker.queued,
            active_jobs=manager.active(),
        )

    async def store_mesh(
        request: Request, response: Response, counts: tuple[int, int],
        blocks: tuple[bool, bool], mesh_id: str | None = None,
    ) -> SceneInfo:
        """Read, hash, decode and keep a scene or mesh body (201 new, 200 known); with
        `mesh_id`, the body must hash to it."""
        (vertices, triangles), (normals, terminator_offsets) = counts, blocks
        t0 = time.perf_counter()
        wire.check_blocks(normals, terminator_offsets)
        expected = wire.scene_body_length(vertices, triangles, normals, terminator_offsets)
        body = await read_body(request, expected)
        t1 = time.perf_counter()
        scene_id = await run_in_threadpool(wire.scene_hash, vertices, triangles, body)
        t2 = time.perf_counter()
        if mesh_id is not None and scene_id != mesh_id:
            raise ApiError(
                422, "mesh_id", f"the body hashes to {scene_id}, not to mesh_id {mesh_id}",
                "name the mesh by its content hash (docs/api.md, the scene id rule), and send "
                "the counts and flags it was hashed with", "mesh_id_mismatch",
            )
        scene = store.get(scene_id)
        if scene is None:  # only new scenes pay for decoding and validation
            try:
                scene = await run_in_threadpool(
                    lambda: wire.decode_scene(body, vertices, triangles, scene_id,
                                              count_degenerate=engine.count_degenerate,
                                              normals=normals,
                                              terminator_offsets=terminator_offsets)
                )
            except (MemoryError, RuntimeError) as exc:
                raise _out_of_memory(exc) from None
            _fits_cache(scene.nbytes, "scene")
            store.put(scene_id, scene, scene.nbytes)
        else:
            response.status_code = 200
        timings = {"read": t1 - t0, "hash": t2 - t1, "decode": time.perf_counter() - t2}
        timings["total"] = time.perf_counter() - t0
        response.headers["Server-Timing"] = _server_timing({k: 1e3 * v for k, v in timings.items()})
        response.headers["Location"] = f"/v1/scenes/{scene_id}"
        response.headers["ETag"] = _etag(scene_id)
        return _scene_info(scene_id, scene)

    def _fits_cache(nbytes: int, what: str) -> None:
        if nbytes > settings.cache_bytes:
            raise ApiError(
                413, "body",
                f"the {what} needs {nbytes} bytes of cache, more than the whole cache "
                f"({settings.cache_bytes})",
                "start the service with a larger --cache-mb", f"{what}_too_large",
            )

    scene_layout = (
        "V*3 little-endian float32 positions, then T*3 little-endian int32 indices "
        "(0-based), then with normals=true T*9 float32 shading normals (three corners "
        "per triangle), then with terminator_offsets=true T float32 shadow terminator "
        "offsets; no header or padding: exactly 12*V + 12*T (+ 36*T) (+ 4*T) bytes."
    )

    uploaded: dict[str, Any] = {  # 201 new, 200 known: what both mesh uploads answer
        "response_model": SceneInfo, "status_code": 201,
        "responses": {200: {"model": SceneInfo, "description": "already known"}, **common},
    }

    @app.post("/v1/scenes", **uploaded, openapi_extra=binary_body(scene_layout + " World space."))
    async def upload_scene(
        request: Request, response: Response, vertices: Vertices, triangles: Triangles,
        normals: Normals = False, terminator_offsets: Offsets = False,
    ) -> SceneInfo:
        """Upload a triangle mesh; its content hash is its id (201 new, 200 known)."""
        return await store_mesh(request, response, (vertices, triangles),
                                (normals, terminator_offsets))

    @app.put("/v1/meshes/{mesh_id}", **uploaded,
             openapi_extra=binary_body(scene_layout + " The mesh's own (object) space."))
    async def put_mesh(
        request: Request, response: Response, mesh_id: SceneId, vertices: Vertices,
        triangles: Triangles, normals: Normals = False, terminator_offsets: Offsets = False,
    ) -> SceneInfo:
        """Upload a mesh of an instance list under its content hash (201 new, 200 known).
        A mesh is a single-mesh scene too: its id works wherever a scene id does."""
        return await store_mesh(request, response, (vertices, triangles),
                                (normals, terminator_offsets), mesh_id)

    @app.head(
        "/v1/meshes/{mesh_id}",
        responses={404: {"description": "unknown mesh"}},
    )
    async def has_mesh(mesh_id: SceneId) -> Response:
        """200 if the service holds this mesh, else 404: clients skip unchanged meshes."""
        if not isinstance(store.get(mesh_id), wire.SceneArrays):
            return Response(status_code=404)
        return Response(status_code=200, headers={"ETag": _etag(mesh_id)})

    @app.post(
        "/v1/instance-scenes",
        response_model=InstanceSceneInfo,
        status_code=201,
        responses={200: {"model": InstanceSceneInfo, "description": "already known"},
                   **error_responses(404, *common)},
        openapi_extra=binary_body(
            "K*32 ASCII hex mesh ids (each PUT /v1/meshes/{mesh_id} first), then N "
            "little-endian int32 mesh indices (0-based into those ids), then N*12 float32 "
            "object-to-world transforms (3x4, row-major); exactly 32*K + 52*N bytes."
        ),
    )
    async def upload_instances(
        request: Request, response: Response,
        meshes: Annotated[int, Query(ge=1, le=2**20)],
        instances: Annotated[int, Query(ge=1, le=2**24)],
    ) -> InstanceSceneInfo:
        """A scene as an instance list over uploaded meshes; its content hash is its id
        (201 new, 200 known). Jobs render it with two levels: the meshes' BVHs, built once
        per mesh, and a top level over the instances."""
        body = await read_body(request, wire.instance_body_length(meshes, instances))
        listing = await run_in_threadpool(wire.decode_instances, body, meshes, instances)
        del body
        scene = store.get(listing.scene_id)
        if scene is None:
            try:
                scene = wire.resolve(listing, lambda mesh_id: _mesh_or_none(store, mesh_id))
            except ValueError as exc:
                raise ApiError(422, "body (mesh ids)", str(exc), "upload the mesh with one "
                               "terminator offset repeated over its triangles",
                               "invalid_parameter") from None
            except KeyError as exc:
                k = listing.mesh_ids.index(exc.args[0])
                raise ApiError(
                    404, "body (mesh ids)",
                    f"mesh id {k} ({exc.args[0]}) is not on this service (or evicted)",
                    "PUT /v1/meshes/{mesh_id} for every mesh the service lacks (HEAD tells)"
                    ", then send the instance list again",
                    "unknown_mesh",
                ) from None
            _fits_cache(scene.nbytes, "scene")
            store.put(listing.scene_id, scene, scene.nbytes)
        else:
            response.status_code = 200
        response.headers["Location"] = f"/v1/scenes/{listing.scene_id}"
        response.headers["ETag"] = _etag(listing.scene_id)
        return _instances_info(scene)

    @app.head(
        "/v1/scenes/{scene_id}",
        responses={304: {"description": "If-None-Match matched"},
                   404: {"description": "unknown scene"}},
    )
    async def has_scene(request: Request, scene_id: SceneId) -> Response:
        """200 if the service holds this scene, else 404: clients skip unchanged uploads."""
        if store.get(scene_id) is None:
            return Response(status_code=404)
        status = 304 if _not_modified(request, scene_id) else 200
        return Response(status_code=status, headers={"ETag": _etag(scene_id)})

    @app.get(
        "/v1/scenes/{scene_id}",
        response_model=SceneInfo | InstanceSceneInfo,
        responses={304: {"description": "If-None-Match matched"}, **error_responses(404, 422)},
    )
    async def scene_info(request: Request, scene_id: SceneId, response: Response) -> Any:
        """What the service knows about a scene."""
        scene = _scene_or_404(store, scene_id)
        if _not_modified(request, scene_id):
            return Response(status_code=304, headers={"ETag": _etag(scene_id)})
        response.headers["ETag"] = _etag(scene_id)
        if isinstance(scene, wire.InstanceScene):
            return _instances_info(scene)
        return _scene_info(scene_id, scene)

    @app.post("/v1/scenes/{scene_id}/bvh", response_model=BvhInfo,
              responses=error_responses(404, *common))
    async def build_bvh(
        request: Request, scene_id: SceneId, spec: BvhRequest, response: Response
    ) -> BvhInfo:
        """Build (or reuse) the scene's BVH with these parameters; per-phase timings.

        A Server-Timing header gives the wait in the device queue and the build's wall
        time in the service (including the statistics the engine computes after it)."""
        t0 = time.perf_counter()
        scene = _scene_or_404(store, scene_id)
        if isinstance(scene, wire.InstanceScene):
            raise ApiError(
                422, "scene_id",
                f"scene {scene_id} is an instance list: its two levels are built by the jobs "
                "and AO requests that render it",
                "render it (POST /v1/jobs); the job status's build says what was built",
                "instance_list",
            )
        started: list[float] = []
        signal = deadline()

        def work() -> tuple[Any, bool]:
            signal.check()  # a build cannot stop half-way: only before it starts
            started.append(time.perf_counter())
            return bvhs.get_or_build_bvh(store, scene, spec.method, spec.leaf_size, settings.device)

        bvh, cached = await run_on_worker(request, signal, "scene", work)
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
            **error_responses(404, *common),
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
        target_error: Annotated[float | None, Query(
            gt=0, lt=1, allow_inf_nan=False, description=TARGET_ERROR_DOC)] = None,
        max_pixel_error: Annotated[float | None, Query(
            gt=0, lt=1, allow_inf_nan=False, description=MAX_PIXEL_ERROR_DOC)] = None,
        engine: Literal["bvh", "dacrt"] = "bvh",
        method: Literal["sah", "median"] | None = None,
        leaf_size: Annotated[int | None, Query(ge=1, le=64)] = None,
    ) -> Response:
        """AO per ray, identical to `kernels.ambient_occlusion` for the same inputs (the
        scene's normals and terminator offsets included).

        Uses the BVH built with `method`/`leaf_size` when given, else the scene's most
        recently used BVH, else builds one with the defaults (sah, 8). Stops when the
        client disconnects or at the deadline (checked between the engine's rounds).
        """
        t0 = time.perf_counter()
        scene = _scene_or_404(store, scene_id)
        params = AoParams(
            spp=spp, distance=distance, seed=seed, target_error=target_error,
            max_pixel_error=max_pixel_error, engine=engine,
        )
        _check_ao(params)
        _check_engine(scene, params)
        _check_work(settings, rays, "rays", params)
        body = await read_body(request, 24 * rays)
        t1 = time.perf_counter()
        try:
            origins, directions = await run_in_threadpool(wire.decode_rays, body, rays)
        except MemoryError as exc:
            raise _out_of_memory(exc) from None
        del body  # the decoded copies are what the work holds
        t2 = time.perf_counter()
        timings: dict[str, float] = {}
        signal = deadline()

        def work() -> np.ndarray:
            # Runs on the worker: pick or build the BVH there, never on the event loop.
            signal.check()
            w0 = time.perf_counter()
            bvh = bvhs.bvh_for_ao(store, scene, method, leaf_size, settings.device)
            w1 = time.perf_counter()
            ao, engine_ms = service_ao.ambient_occlusion(bvh, scene, origins, directions, params,
                                                   signal)
            timings.update(bvh=1000 * (w1 - w0), ao=1000 * (time.perf_counter() - w1))
            timings.update({f"ao.{k}": v for k, v in engine_ms.items() if k != "total"})
            return ao

        ao = await run_on_worker(request, signal, "rays", work)
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
    async def create_job(request: JobRequest, response: Response) -> JobStatus:
        """Queue an AO render of `camera`'s pixels; poll it, stream its events, fetch it."""
        try:
            camera = camera_render.job_camera(request)
        except ValueError as exc:
            raise ApiError(
                422,
                "camera",
                str(exc),
                "correct the camera field named in the message (see kernels/render/camera.py)",
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
        params = service_ao.ao_params(request)
        _check_ao(params)
        _check_work(settings, camera.width * camera.height, "camera.width x camera.height",
                    params)
        scene = _scene_or_404(store, request.scene_id)
        _check_engine(scene, params)

        def work(job: jobs.Job) -> None:
            camera_render.render_camera(
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
        response.headers["Location"] = f"/v1/jobs/{job.job_id}"
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
        """Cancel a job: a queued one never starts (and frees its place in the queue), a
        running one stops at its next step."""
        job = job_or_404(job_id)
        manager.cancel(job_id)
        return JobStatus(**job.snapshot())

    @app.get(
        "/v1/jobs/{job_id}/result",
        response_class=Response,
        responses={
            200: {
                "content": {
                    OCTET: {"schema": {"type": "string", "format": "binary"}},
                    "image/png": {"schema": {"type": "string", "format": "binary"}},
                },
                "description": "format=f32: height*width little-endian float32 AO, row 0 "
                "at the top; format=coverage: the same layout, 1.0 where the camera ray "
                "hit and 0.0 where it missed; format=depth: the same layout, the hit's "
                "camera-space depth (Cycles' Z pass), 1e10 where it missed; format=png: "
                "8-bit grayscale PNG of the AO. X-Width/X-Height headers.",
            },
            **error_responses(404, 409, 422),
        },
    )
    async def job_result(
        job_id: JobId, format: Literal["f32", "coverage", "depth", "png"] = "f32"
    ) -> Response:
        """The finished image (AO, coverage or depth); 409 while the job is not done."""
        job = job_or_404(job_id)
        # One read: the manager may forget the job meanwhile.
        layer = {"f32": job.ao, "coverage": job.coverage, "depth": job.depth}.get(format)
        png = job.png
        if job.state != "done" or png is None or (format != "png" and layer is None):
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
            return Response(png, media_type="image/png", headers=headers)
        payload = await run_in_threadpool(wire.encode_f32, layer)
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
            **error_responses(404, 422, 429),
        },
    )
    async def job_events(job_id: JobId, request: Request) -> StreamingResponse:
        """Progress as server-sent events until the job ends or the client leaves."""
        job = job_or_404(job_id)
        if job.streams >= settings.max_streams_per_job:
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
                async for event in jobs.job_events(job, request.is_disconnected):
                    yield event
            finally:
                release()

        return StreamingResponse(
            events(),
            media_type="text/event-stream",
            headers={"Cache-Control": "no-cache"},
            background=BackgroundTask(release),
        )

    with_bearer_scheme(app)
    return app


def with_bearer_scheme(app: FastAPI) -> None:
    """Declare the token in the schema, so that /docs has an Authorize button for it."""
    make = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            schema = make()
            schema.setdefault("components", {})["securitySchemes"] = {
                BEARER: {"type": "http", "scheme": "bearer",
                         "description": "the token that `scenesort token` prints"}
            }
            schema["security"] = [{BEARER: []}]
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]


def _instances_info(scene: wire.InstanceScene) -> InstanceSceneInfo:
    return InstanceSceneInfo(
        scene_id=scene.scene_id,
        meshes=[m.scene_id for m in scene.meshes],
        instances=scene.instances,
        triangles=scene.triangles,
        bounds=scene.bounds,
        bytes=scene.nbytes,
    )


def _scene_info(scene_id: str, scene: wire.SceneArrays) -> SceneInfo:
    return SceneInfo(
        scene_id=scene_id,
        vertices=len(scene.vertices),
        triangles=len(scene.indices),
        bounds=scene.bounds,
        degenerate=scene.degenerate,
        normals=scene.normals is not None,
        bytes=scene.nbytes,
    )


def stop_work(app: FastAPI) -> None:
    """Cancel every job and running request (SIGTERM/SIGINT): they end at their next
    round, and queued ones never start."""
    app.state.jobs.cancel_all(SHUTDOWN)
    for signal in list(app.state.live):
        signal.stop(SHUTDOWN)
