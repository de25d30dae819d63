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
import queue
import threading
import time
import uuid
from collections import OrderedDict
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

log = logging.getLogger("scenesort.jobs")

JobState = Literal["queued", "running", "done", "failed", "cancelled"]
FINAL_STATES: frozenset[str] = frozenset({"done", "failed", "cancelled"})


class QueueFull(Exception):
    """The device queue is at capacity; the client should retry later (HTTP 429)."""


class JobCancelled(Exception):
    """Raised inside a job's work when its cancel flag is seen (at the next report)."""


class DeviceWorker:
    """One thread that runs submitted callables in order on one device."""

    def __init__(self, device: str, max_queue: int = 64) -> None:
        self.device = device
        self._queue: queue.Queue[tuple[concurrent.futures.Future, Callable[[], Any]] | None]
        self._queue = queue.Queue(maxsize=max_queue)
        self._thread = threading.Thread(target=self._loop, name=f"worker-{device}", daemon=True)
        self._thread.start()

    def submit(self, fn: Callable[[], Any]) -> concurrent.futures.Future:
        """Queue `fn`; its future resolves with its result or exception. Raise QueueFull."""
        future: concurrent.futures.Future = concurrent.futures.Future()
        try:
            self._queue.put_nowait((future, fn))
        except queue.Full:
            raise QueueFull(f"{self._queue.maxsize} tasks already queued") from None
        return future

    async def run(self, fn: Callable[[], Any]) -> Any:
        """Submit `fn` and await its result from the event loop."""
        return await asyncio.wrap_future(self.submit(fn))

    @property
    def queued(self) -> int:
        return self._queue.qsize()

    def stop(self, timeout: float = 5.0) -> None:
        """Let queued work finish, then end the thread (bounded wait; it is a daemon)."""
        try:
            self._queue.put(None, timeout=timeout)
        except queue.Full:
            return
        self._thread.join(timeout)

    def _loop(self) -> None:
        while True:
            item = self._queue.get()
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
    """A camera render: its state as clients see it, and its result once done."""

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
    png: bytes | None = None
    spp_mean: float | None = None
    version: int = 0  # bumped on every change; server-sent events wait on it
    cancel_requested: threading.Event = field(default_factory=threading.Event)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    @property
    def result_nbytes(self) -> int:
        """Bytes held by the finished image (float32 and PNG)."""
        return (self.ao.nbytes if self.ao is not None else 0) + len(self.png or b"")

    def report(self, phase: str | None = None, progress: float | None = None) -> None:
        """Update phase/progress from the worker; raise JobCancelled once cancel is asked."""
        if self.cancel_requested.is_set():
            raise JobCancelled(self.job_id)
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

    def finish(self, state: JobState, error: str | None = None) -> None:
        with self._lock:
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
                "error": self.error,
            }


class JobManager:
    """Creates jobs on a worker, finds them by id, cancels them; keeps the newest few
    finished ones, bounded in count and in the bytes of their images."""

    def __init__(
        self, worker: DeviceWorker, keep_finished: int = 32, result_bytes: int = 512 * 2**20
    ) -> None:
        self.worker = worker
        self.keep_finished = keep_finished
        self.result_bytes = result_bytes
        self._jobs: OrderedDict[str, Job] = OrderedDict()
        self._lock = threading.Lock()

    def create(self, scene_id: str, width: int, height: int, work: Callable[[Job], None]) -> Job:
        """Queue `work(job)`; it fills `job.ao`/`job.png` and reports progress."""
        job = Job(job_id=uuid.uuid4().hex[:16], scene_id=scene_id, width=width, height=height)
        self.worker.submit(lambda: self._run(job, work))  # QueueFull propagates: HTTP 429
        with self._lock:
            self._jobs[job.job_id] = job
            self._forget_old()
        return job

    def get(self, job_id: str) -> Job | None:
        with self._lock:
            return self._jobs.get(job_id)

    def cancel(self, job_id: str) -> Job | None:
        """Ask the job to stop; a queued job never starts, a running one stops at its next
        progress report."""
        job = self.get(job_id)
        if job is not None and job.state not in FINAL_STATES:
            job.cancel_requested.set()
            if job.state == "queued":
                job.finish("cancelled")
        return job

    def active(self) -> int:
        with self._lock:
            return sum(1 for j in self._jobs.values() if j.state not in FINAL_STATES)

    def _forget_old(self) -> None:
        """Drop the oldest finished jobs past the count or byte bound (lock held)."""
        finished = [j for j in self._jobs.values() if j.state in FINAL_STATES]
        held = sum(j.result_nbytes for j in finished)
        for job in finished:  # oldest first
            if len(finished) <= self.keep_finished and held <= self.result_bytes:
                break
            del self._jobs[job.job_id]
            finished = finished[1:]
            held -= job.result_nbytes

    @staticmethod
    def _run(job: Job, work: Callable[[Job], None]) -> None:
        if job.cancel_requested.is_set():
            return  # cancelled while queued: already final
        with job._lock:
            job.state = "running"
            job.version += 1
        start = time.perf_counter()
        try:
            work(job)
        except JobCancelled:
            job.finish("cancelled")
        except ValueError as exc:  # the engine rejected the input: the client's to fix
            job.finish("failed", f"invalid input: {exc}")
        except Exception as exc:  # noqa: BLE001 - an engine fault fails this job, not the worker
            log.exception("job %s failed", job.job_id)
            job.finish("failed", f"internal error: {type(exc).__name__}: {exc}")
        else:
            job.finish("done")
        finally:
            job.add_timing("total", 1000.0 * (time.perf_counter() - start))


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
    engine: Literal["bvh", "dacrt"] = "bvh"

    def kwargs(self) -> dict[str, Any]:
        """Keyword arguments for `kernels.ambient_occlusion` / `kernels.render_ao`."""
        out: dict[str, Any] = {"spp": self.spp, "seed": self.seed}
        if self.distance is not None:
            out["distance"] = self.distance
        if self.target_error is not None:
            out["target_error"] = self.target_error
        out["engine"] = self.engine
        return out


def warm_up(device: str) -> None:
    """Build and render a one-triangle scene so that Warp loads (or compiles) every kernel
    module now; a failure is logged and left for real requests to report."""
    try:
        import kernels

        vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
        bvh = kernels.build_bvh(vertices, np.array([[0, 1, 2]], np.int32), device=device)
        rays = np.array([[0.2, 0.2, 1.0]], np.float32), np.array([[0, 0, -1]], np.float32)
        kernels.render_ao(bvh, *rays, spp=1)
    except Exception:  # noqa: BLE001 - never stop the service over a warm-up
        log.exception("warm-up on %s failed", device)


def get_or_build_bvh(
    store: Any, scene: Any, method: str, leaf_size: int, device: str
) -> tuple[Any, bool]:
    """The BVH for these parameters from the store, else built and stored; (bvh, cached)."""
    from backend.store import bvh_key, bvh_nbytes

    key = bvh_key(scene.scene_id, method, leaf_size)
    bvh = store.get(key)
    if bvh is not None:
        return bvh, True
    import kernels  # the engine is imported only where it is used

    bvh = kernels.build_bvh(
        scene.vertices, scene.indices, method=method, leaf_size=leaf_size, device=device
    )
    store.put(key, bvh, bvh_nbytes(bvh))
    return bvh, False


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
    from kernels.render import ao

    return int(getattr(ao, "DEFAULT_MAX_SPP", 1024))


def ambient_occlusion(
    bvh: Any, origins: np.ndarray, directions: np.ndarray, params: AoParams
) -> tuple[np.ndarray, dict[str, float]]:
    """AO for explicit rays, exactly `kernels.ambient_occlusion` (which is
    `render_ao(...).ao`), with the engine's phase timings."""
    import kernels

    result = kernels.render_ao(bvh, origins, directions, **params.kwargs())
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
) -> None:
    """A camera job: BVH (cached or built), primary rays, AO with progress, PNG."""
    from backend.wire import encode_png

    def timed(phase: str, fn: Callable[[], Any]) -> Any:
        job.report(phase)  # also the cancellation point between phases
        start = time.perf_counter()
        out = fn()
        job.add_timing(phase, 1000.0 * (time.perf_counter() - start))
        return out

    bvh, cached = timed("bvh", lambda: get_or_build_bvh(store, scene, method, leaf_size, device))
    if not cached:  # of "bvh", the part that was Warp compiling (as "ao.compile" of "ao")
        job.add_timing("bvh.compile", float(bvh.stats.get("compile_ms", 0.0)))
    origins, directions, tmin, tmax = timed("camera", camera.rays)
    ao, spp_used = timed(
        "ao", lambda: _render_ao(job, bvh, origins, directions, tmin, tmax, params)
    )
    job.ao = ao.reshape(camera.height, camera.width)
    hit = spp_used > 0  # rays that missed take no samples
    job.spp_mean = float(spp_used[hit].mean()) if hit.any() else 0.0
    job.png = timed("png", lambda: encode_png(job.ao))


def _render_ao(
    job: Job,
    bvh: Any,
    origins: np.ndarray,
    directions: np.ndarray,
    tmin: np.ndarray,
    tmax: np.ndarray,
    params: AoParams,
) -> tuple[np.ndarray, np.ndarray]:
    """`kernels.render_ao` within the camera's clip range, reporting progress between its
    rounds; (ao, spp used per ray)."""
    import kernels

    def progress(fraction: float, phase: str) -> None:
        job.report(f"ao.{phase}", fraction)  # raises JobCancelled inside the engine's loop

    result = kernels.render_ao(
        bvh, origins, directions, tmin=tmin, tmax=tmax, progress=progress, **params.kwargs()
    )
    for name, ms in result.timings_ms.items():
        job.add_timing(f"ao.{name}", float(ms))
    return np.asarray(result.ao, dtype=np.float32), np.asarray(result.spp_used)
