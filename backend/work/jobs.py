"""Jobs: long renders on a device worker, with state, progress, timings, deadlines and
cancel, found by id; their progress as server-sent events.

The event loop only reads job records; the work runs on the worker (`worker.DeviceWorker`)
and reports progress through `Job.report`, which is also where it learns to stop.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import json
import logging
import threading
import time
import uuid
from collections import OrderedDict
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any, Literal, TypeVar

import numpy as np
from scenesort.backend.work.stop import Stopped, StopSignal
from scenesort.backend.work.worker import DeviceWorker, QueueFull

T = TypeVar("T")

log = logging.getLogger("scenesort.jobs")

JobState = Literal["queued", "running", "done", "failed", "cancelled"]
FINAL_STATES: frozenset[str] = frozenset({"done", "failed", "cancelled"})
TOO_LARGE = "the scene or the render is too large for this machine's memory"


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
    holdout: np.ndarray | None = None  # (height, width) float32: 1 where a holdout is seen
    # the extra images a request asked for (JobRequest.passes), by name: normal and
    # position (height, width, 3), object (height, width); float32
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    # a camera job's AO is a picture: render.camera_render.job_png makes its PNG when first
    # asked for (a client reading floats, as F12 and the viewport do, never pays ~10 ms of zlib)
    picture: bool = False
    png: bytes | None = None
    spp_mean: float | None = None
    # what the render achieved (AoResult.stats): estimated RMSE, largest spp, rays traced
    rmse_estimate: float | None = None
    spp_max: int | None = None
    rays: int | None = None
    build: Any = None  # backend.frames.BuildReport: what the job built, refit or reused
    denoised: bool | None = None
    film: str | None = None  # the pixels' film: JobStatus.film (wire/models.py)
    version: int = 0  # bumped on every change; server-sent events wait on it
    signal: StopSignal = field(default_factory=StopSignal)
    max_seconds: float = float("inf")  # the deadline, counted from the start of the run
    streams: int = 0  # event streams open on this job
    future: concurrent.futures.Future | None = field(default=None, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    @property
    def result_nbytes(self) -> int:
        """Bytes held by the finished images (float32 layers and PNG)."""
        layers = (self.ao, self.coverage, self.depth, self.holdout, *self.extras.values())
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

    def timed(self, phase: str, fn: Callable[[], T]) -> T:
        """fn() as the job's phase `phase` (reported first: also the cancellation point
        between phases), its milliseconds kept under that name."""
        self.report(phase)
        start = time.perf_counter()
        out = fn()
        self.add_timing(phase, 1000.0 * (time.perf_counter() - start))
        return out

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
        """The JSON status of the job (the `JobStatus` model in wire/models.py)."""
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
                "film": self.film,
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
        """Queue `work(job)`; it fills `job.ao` and reports progress."""
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
        state: JobState = "done"
        error: str | None = None
        try:
            work(job)
        except Stopped as exc:
            state, error = "cancelled" if job.signal.stopped else "failed", str(exc)
        except ValueError as exc:  # the engine rejected the input: the client's to fix
            state, error = "failed", f"invalid input: {exc}"
        except MemoryError:
            state, error = "failed", TOO_LARGE
        except Exception as exc:  # noqa: BLE001 - an engine fault fails this job, not the worker
            log.exception("job %s failed", job.job_id)
            state, error = "failed", f"internal error: {type(exc).__name__}: {exc}"
        finally:  # before it is final: whoever sees it final sees its whole time
            job.add_timing("total", 1000.0 * (time.perf_counter() - start))
        job.finish(state, error)
        self._forget_old()  # a finished image counts against the budget now


async def until_final(job: Job, timeout: float) -> None:
    """Return once `job` is final (its worker task over), or after `timeout` seconds: a
    long poll, so that a client sees a short job end when it ends, not at its next poll."""
    if job.future is None or job.snapshot()["state"] in FINAL_STATES:
        return
    await asyncio.wait({asyncio.wrap_future(job.future)}, timeout=timeout)


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
