"""Heavy work off the event loop: one worker thread per device, jobs with progress.

A Warp CPU launch is one serial loop on one core (WARP_FACTS.md), and a device runs one
launch well at a time, so each device gets exactly one `DeviceWorker` draining a
bounded queue. Short requests (BVH build, AO on explicit rays) and long camera renders
(`Job`) share that queue; the event loop only awaits futures and reads job records.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import json
import logging
import threading
import time
import uuid
from collections import OrderedDict, deque
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from scenesort.backend.render.frames import View, scene_bvh

log = logging.getLogger("scenesort.jobs")

JobState = Literal["queued", "running", "done", "failed", "cancelled"]
FINAL_STATES: frozenset[str] = frozenset({"done", "failed", "cancelled"})
TOO_LARGE = "the scene or the render is too large for this machine's memory"


class QueueFull(Exception):
    """The device queue is at capacity; the client should retry later (HTTP 429)."""


class Stopped(Exception):
    """Work stopped before its end; the message says why (cancelled, past its deadline,
    the service stopping). Raised inside the work at its next progress report."""


@dataclass(eq=False)  # compared and hashed by identity: kept in a set of live work
class StopSignal:
    """How work learns it must stop: a flag with its reason, and a deadline."""

    deadline: float = float("inf")  # time.monotonic() after which the work fails
    reason: str | None = None
    _flag: threading.Event = field(default_factory=threading.Event, repr=False)

    def stop(self, reason: str) -> None:
        if not self._flag.is_set():
            self.reason = reason
            self._flag.set()

    @property
    def stopped(self) -> bool:
        return self._flag.is_set()

    def check(self) -> None:
        """Raise Stopped if the work should end now (called between the engine's rounds)."""
        if self._flag.is_set():
            raise Stopped(self.reason or "cancelled")
        if time.monotonic() > self.deadline:
            raise Stopped("past the deadline (serve --max-seconds)")


class DeviceWorker:
    """One thread that runs submitted callables in order on one device.

    The queue holds at most `max_queue` live tasks: a task whose future was cancelled
    before it started frees its slot at once."""

    def __init__(self, device: str, max_queue: int = 64) -> None:
        self.device = device
        self.max_queue = max_queue
        self._pending: deque[tuple[concurrent.futures.Future, Callable[[], Any]] | None]
        self._pending = deque()
        self._ready = threading.Condition()
        self._thread = threading.Thread(target=self._loop, name=f"worker-{device}", daemon=True)
        self._thread.start()

    def submit(self, fn: Callable[[], Any]) -> concurrent.futures.Future:
        """Queue `fn`; its future resolves with its result or exception. Raise QueueFull."""
        future: concurrent.futures.Future = concurrent.futures.Future()
        with self._ready:
            if self._live() >= self.max_queue:
                raise QueueFull(f"{self.max_queue} tasks already queued")
            self._pending.append((future, fn))
            self._ready.notify()
        return future

    async def run(self, fn: Callable[[], Any]) -> Any:
        """Submit `fn` and await its result from the event loop."""
        return await asyncio.wrap_future(self.submit(fn))

    def _live(self) -> int:
        """Queued tasks not cancelled (lock held); drops the cancelled ones."""
        kept = [item for item in self._pending if item is None or not item[0].cancelled()]
        if len(kept) != len(self._pending):
            self._pending = deque(kept)
        return len(kept)

    @property
    def queued(self) -> int:
        with self._ready:
            return self._live()

    def stop(self, timeout: float = 5.0) -> bool:
        """Cancel what is queued, let the running task end, stop the thread (bounded
        wait; it is a daemon). True if the thread ended within `timeout`."""
        with self._ready:
            for item in self._pending:
                if item is not None:
                    item[0].cancel()
            self._pending = deque([None])
            self._ready.notify()
        self._thread.join(timeout)
        return not self._thread.is_alive()

    def _loop(self) -> None:
        while True:
            with self._ready:
                while not self._pending:
                    self._ready.wait()
                item = self._pending.popleft()
            if item is None:
                return
            future, fn = item
            if not future.set_running_or_notify_cancel():
                continue
            try:
                future.set_result(fn())
            except BaseException as exc:  # noqa: BLE001 - the future carries it to the caller
                future.set_exception(exc)


@dataclass
class Job:
    """A camera render: its state as clients see it, and its result once done.

    Every change of `state` happens under `_lock`, so a cancel and the worker's start
    cannot interleave: a job cancelled while queued never runs."""

    job_id: str
    scene_id: str
    width: int
    height: int
    state: JobState = "queued"
    phase: str = "queued"
    progress: float = 0.0
    timings_ms: dict[str, float] = field(default_factory=dict)
    error: str | None = None
    created: float = field(default_factory=time.time)
    ao: np.ndarray | None = None  # (height, width) float32 once done
    coverage: np.ndarray | None = None  # (height, width) float32: 1 where the camera ray hit
    depth: np.ndarray | None = None  # (height, width) float32 camera-space Z, 1e10 on a miss
    png: bytes | None = None
    spp_mean: float | None = None
    # what the render achieved (AoResult.stats): estimated RMSE, largest spp, rays traced
    rmse_estimate: float | None = None
    spp_max: int | None = None
    rays: int | None = None
    build: Any = None  # backend.frames.BuildReport: what the job built, refit or reused
    denoised: bool | None = None
    version: int = 0  # bumped on every change; server-sent events wait on it
    signal: StopSignal = field(default_factory=StopSignal)
    max_seconds: float = float("inf")  # the deadline, counted from the start of the run
    streams: int = 0  # event streams open on this job
    future: concurrent.futures.Future | None = field(default=None, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    @property
    def result_nbytes(self) -> int:
        """Bytes held by the finished images (float32 layers and PNG)."""
        layers = (self.ao, self.coverage, self.depth)
        return sum(a.nbytes for a in layers if a is not None) + len(self.png or b"")

    def report(self, phase: str | None = None, progress: float | None = None) -> None:
        """Update phase/progress from the worker; raise Stopped once it must stop."""
        self.signal.check()
        with self._lock:
            if phase is not None:
                self.phase = phase
            if progress is not None:
                self.progress = float(min(max(progress, 0.0), 1.0))
            self.version += 1

    def add_timing(self, name: str, ms: float) -> None:
        with self._lock:
            self.timings_ms[name] = round(ms, 3)
            self.version += 1

    def start(self) -> bool:
        """Queued -> running, unless it was cancelled first; whether it may run."""
        with self._lock:
            if self.state != "queued" or self.signal.stopped:
                return False
            self.state = "running"
            self.signal.deadline = time.monotonic() + self.max_seconds
            self.version += 1
            return True

    def cancel(self, reason: str) -> None:
        """Stop the job: a queued one is final now, a running one at its next report."""
        with self._lock:
            if self.state in FINAL_STATES:
                return
            self.signal.stop(reason)
            if self.state == "queued":
                self._make_final("cancelled", reason)
        if self.future is not None:
            self.future.cancel()  # a queued task frees its worker slot

    def finish(self, state: JobState, error: str | None = None) -> None:
        """Make the job final (once: a final state is never changed)."""
        with self._lock:
            if self.state not in FINAL_STATES:
                self._make_final(state, error)

    def _make_final(self, state: JobState, error: str | None) -> None:
        self.state = state
        self.error = error
        if state == "done":
            self.progress = 1.0
        self.phase = state
        self.version += 1

    def snapshot(self) -> dict[str, Any]:
        """The JSON status of the job (the `JobStatus` model in app.py)."""
        with self._lock:
            return {
                "job_id": self.job_id,
                "scene_id": self.scene_id,
                "state": self.state,
                "phase": self.phase,
                "progress": self.progress,
                "width": self.width,
                "height": self.height,
                "timings_ms": dict(self.timings_ms),
                "spp_mean": self.spp_mean,
                "spp_max": self.spp_max,
                "rmse_estimate": self.rmse_estimate,
                "rays": self.rays,
                "build": None if self.build is None else self.build.to_dict(),
                "denoised": self.denoised,
                "error": self.error,
            }


class JobManager:
    """Creates jobs on a worker, finds them by id, cancels them; keeps the newest few
    finished ones, bounded in count and in the bytes of their images (counted as each
    job finishes)."""

    def __init__(
        self,
        worker: DeviceWorker,
        keep_finished: int = 32,
        result_bytes: int = 512 * 2**20,
        max_seconds: float = float("inf"),
    ) -> None:
        self.worker = worker
        self.keep_finished = keep_finished
        self.result_bytes = result_bytes
        self.max_seconds = max_seconds
        self._jobs: OrderedDict[str, Job] = OrderedDict()
        self._lock = threading.Lock()

    def create(self, scene_id: str, width: int, height: int, work: Callable[[Job], None]) -> Job:
        """Queue `work(job)`; it fills `job.ao`/`job.png` and reports progress."""
        job = Job(job_id=uuid.uuid4().hex[:16], scene_id=scene_id, width=width, height=height,
                  max_seconds=self.max_seconds)
        with self._lock:  # before the worker can finish it, so _forget_old sees it
            self._jobs[job.job_id] = job
        try:
            job.future = self.worker.submit(lambda: self._run(job, work))
        except QueueFull:
            with self._lock:
                del self._jobs[job.job_id]
            raise  # HTTP 429
        return job

    def get(self, job_id: str) -> Job | None:
        with self._lock:
            return self._jobs.get(job_id)

    def cancel(self, job_id: str, reason: str = "cancelled by the client") -> Job | None:
        """Cancel one job (see `Job.cancel`)."""
        job = self.get(job_id)
        if job is not None:
            job.cancel(reason)
            self._forget_old()
        return job

    def cancel_all(self, reason: str) -> None:
        """Cancel every job that has not finished (the service is stopping)."""
        with self._lock:
            jobs = list(self._jobs.values())
        for job in jobs:
            job.cancel(reason)

    def active(self) -> int:
        with self._lock:
            return sum(1 for j in self._jobs.values() if j.state not in FINAL_STATES)

    def _forget_old(self) -> None:
        """Drop the oldest finished jobs past the count or byte bound."""
        with self._lock:
            finished = [j for j in self._jobs.values() if j.state in FINAL_STATES]
            held = sum(j.result_nbytes for j in finished)
            for job in finished:  # oldest first
                if len(finished) <= self.keep_finished and held <= self.result_bytes:
                    break
                del self._jobs[job.job_id]
                finished = finished[1:]
                held -= job.result_nbytes

    def _run(self, job: Job, work: Callable[[Job], None]) -> None:
        if not job.start():
            return  # cancelled while queued: already final
        start = time.perf_counter()
        try:
            work(job)
        except Stopped as exc:
            job.finish("cancelled" if job.signal.stopped else "failed", str(exc))
        except ValueError as exc:  # the engine rejected the input: the client's to fix
            job.finish("failed", f"invalid input: {exc}")
        except MemoryError:
            job.finish("failed", TOO_LARGE)
        except Exception as exc:  # noqa: BLE001 - an engine fault fails this job, not the worker
            log.exception("job %s failed", job.job_id)
            job.finish("failed", f"internal error: {type(exc).__name__}: {exc}")
        else:
            job.finish("done")
        finally:
            job.add_timing("total", 1000.0 * (time.perf_counter() - start))
            self._forget_old()  # a finished image counts against the budget now


async def job_events(
    job: Job,
    is_disconnected: Callable[[], Awaitable[bool]],
    poll_s: float = 0.05,
    heartbeat_s: float = 10.0,
) -> AsyncIterator[str]:
    """Server-sent events: one `progress` event per change, then a final `end` event.

    Polls the job record (cheap) rather than crossing threads with callbacks; stops when
    the job is final or the client has gone.
    """
    seen = -1
    last_sent = time.monotonic()
    while True:
        version, snapshot = job.version, job.snapshot()
        final = snapshot["state"] in FINAL_STATES
        if version != seen:
            seen = version
            last_sent = time.monotonic()
            yield f"event: {'end' if final else 'progress'}\ndata: {json.dumps(snapshot)}\n\n"
        if final or await is_disconnected():
            return
        if time.monotonic() - last_sent > heartbeat_s:
            last_sent = time.monotonic()
            yield ": keep-alive\n\n"
        await asyncio.sleep(poll_s)


# --- the work itself (runs on the device worker, never on the event loop) ------------


@dataclass(frozen=True)
class AoParams:
    """AO settings shared by the explicit-ray route and camera jobs."""

    spp: int = 16
    distance: float | None = None
    seed: int = 0
    target_error: float | None = None
    max_pixel_error: float | None = None
    engine: Literal["bvh", "dacrt"] = "bvh"
    threads: int | None = None  # host threads (None: all); results do not depend on it
    denoise: bool = False  # camera jobs only: OIDN on the image

    @property
    def adaptive(self) -> bool:
        return self.target_error is not None or self.max_pixel_error is not None

    def kwargs(self) -> dict[str, Any]:
        """Keyword arguments for `kernels.ambient_occlusion` / `kernels.render_ao`."""
        out: dict[str, Any] = {"spp": self.spp, "seed": self.seed}
        if self.distance is not None:
            out["distance"] = self.distance
        if self.target_error is not None:
            out["target_error"] = self.target_error
        if self.max_pixel_error is not None:
            out["max_pixel_error"] = self.max_pixel_error
        out["engine"] = self.engine
        if self.threads is not None:
            out["threads"] = self.threads
        return out


def ao_params(request: Any, threads: int | None = None) -> AoParams:
    """The AO settings of a job request (models.JobRequest, or a frame of a bundle)."""
    return AoParams(
        spp=request.spp,
        distance=request.distance,
        seed=request.seed,
        target_error=request.target_error,
        max_pixel_error=request.max_pixel_error,
        engine=request.engine,
        threads=threads,
        denoise=request.denoise,
    )


def job_camera(request: Any) -> Any:
    """The framed camera of a job request (its camera, window and pixel aspect); raises
    ValueError naming the camera field at fault."""
    from scenesort.backend.render.framing import framed

    window = None if request.window is None else request.window.model_dump()
    return framed(request.camera.model_dump(), window, request.pixel_aspect)


def warm_up(device: str) -> None:
    """Build and render a one-triangle scene so that Warp loads (or compiles) every kernel
    module now; a failure is logged and left for real requests to report."""
    try:
        from scenesort import kernels

        vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
        bvh = kernels.build_bvh(vertices, np.array([[0, 1, 2]], np.int32), device=device)
        rays = np.array([[0.2, 0.2, 1.0]], np.float32), np.array([[0, 0, -1]], np.float32)
        kernels.render_ao(bvh, *rays, spp=1)
    except Exception:  # noqa: BLE001 - never stop the service over a warm-up
        log.exception("warm-up on %s failed", device)


def get_or_build_bvh(
    store: Any, scene: Any, method: str, leaf_size: int, device: str
) -> tuple[Any, bool]:
    """What a scene traces with these parameters (a mesh's BVH, or an instance list's two
    levels) from the store, else made and stored; (bvh, cached)."""
    bvh, report = scene_bvh(store, scene, method, leaf_size, device)
    return bvh, report.cached


def bvh_for_ao(
    store: Any, scene: Any, method: str | None, leaf_size: int | None, device: str
) -> Any:
    """The BVH an AO request uses: the one asked for (built if missing); with neither
    parameter, the scene's most recently used BVH, else a new sah/8 one."""
    if method is None and leaf_size is None:
        latest = store.latest_with_prefix(f"{scene.scene_id}/bvh/")
        if latest is not None:
            store.get(latest[0])  # a use: refresh its age
            return latest[1]
    bvh, _ = get_or_build_bvh(store, scene, method or "sah", leaf_size or 8, device)
    return bvh


def adaptive_max_spp() -> int:
    """The engine's cap on samples per ray in adaptive (target_error) mode."""
    from scenesort.kernels.render import ao

    return int(getattr(ao, "DEFAULT_MAX_SPP", 1024))


def ambient_occlusion(
    bvh: Any, scene: Any, origins: np.ndarray, directions: np.ndarray, params: AoParams,
    signal: StopSignal,
) -> tuple[np.ndarray, dict[str, float]]:
    """AO for explicit rays, exactly `kernels.ambient_occlusion` (which is
    `render_ao(...).ao`) with the scene's normals, with the engine's phase timings;
    `signal` is checked between the engine's rounds (it raises Stopped there)."""
    from scenesort import kernels

    result = kernels.render_ao(
        bvh, origins, directions, progress=lambda *_: signal.check(), **params.kwargs(),
        **scene.shading(),
    )
    return np.asarray(result.ao, dtype=np.float32), dict(result.timings_ms)


def render_camera(
    job: Job,
    store: Any,
    scene: Any,
    camera: Any,
    params: AoParams,
    method: str,
    leaf_size: int,
    device: str,
    cull: bool = True,
) -> None:
    """A camera job: BVH (cached or built; with `cull`, of an instance list only what the
    camera may see: backend/frames.py), primary rays, AO with progress, the primary hits'
    depth and coverage, PNG."""
    from scenesort.backend.wire.binary import encode_png

    def timed(phase: str, fn: Callable[[], Any]) -> Any:
        job.report(phase)  # also the cancellation point between phases
        start = time.perf_counter()
        out = fn()
        job.add_timing(phase, 1000.0 * (time.perf_counter() - start))
        return out

    view = View(camera, params.distance) if cull else None
    bvh, job.build = timed("bvh", lambda: scene_bvh(store, scene, method, leaf_size, device,
                                                    view))
    if not job.build.cached:  # of "bvh", the part that was Warp compiling (as "ao.compile")
        job.add_timing("bvh.compile", float(getattr(bvh, "stats", {}).get("compile_ms", 0.0)))
    origins, directions, tmin, tmax = timed("camera", camera.rays)
    shape = (camera.height, camera.width)
    result = timed(
        "ao", lambda: _render_ao(job, bvh, scene, origins, directions, tmin, tmax, params, shape)
    )
    job.ao = np.asarray(result.ao, dtype=np.float32).reshape(shape)
    job.coverage = (result.spp_used > 0).astype(np.float32).reshape(shape)  # misses: 0 spp
    stats = result.stats()
    job.spp_mean, job.spp_max = stats["spp_mean"], stats["spp_max"]
    job.rmse_estimate, job.rays = stats["rmse_estimate"], stats["rays"]
    job.denoised = stats["denoised"]
    depth = timed("depth", lambda: camera_depth(bvh, camera, origins, directions, tmin, tmax))
    job.depth = depth.reshape(shape)
    job.png = timed("png", lambda: encode_png(job.ao))


BACKGROUND_DEPTH = 1e10  # Cycles' Z pass on background pixels


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


def _render_ao(
    job: Job,
    bvh: Any,
    scene: Any,
    origins: np.ndarray,
    directions: np.ndarray,
    tmin: np.ndarray,
    tmax: np.ndarray,
    params: AoParams,
    shape: tuple[int, int],
) -> Any:
    """`kernels.render_ao` within the camera's clip range with the scene's normals,
    reporting progress between its rounds, denoised if asked (an image of `shape`); its
    `AoResult`."""
    from scenesort import kernels

    def progress(fraction: float, phase: str) -> None:
        job.report(f"ao.{phase}", fraction)  # raises Stopped inside the engine's loop

    result = kernels.render_ao(
        bvh, origins, directions, tmin=tmin, tmax=tmax, progress=progress, **params.kwargs(),
        **scene.shading(), denoise=params.denoise, image_shape=shape,
    )
    for name, ms in result.timings_ms.items():
        job.add_timing(f"ao.{name}", float(ms))
    return result
