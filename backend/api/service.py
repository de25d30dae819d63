"""What every route shares: the settings `scenesort serve` gives, and one `Service` per app
(on `app.state.service`) holding the store, the device worker, the jobs and the work in
flight. Routes get it as a dependency (`Shared`)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Annotated, Any

from fastapi import Depends, Request
from scenesort.backend.api.errors import SHUTDOWN
from scenesort.backend.api.security import Policy
from scenesort.backend.wire.problems import ApiError
from scenesort.backend.work.jobs import Job, JobManager
from scenesort.backend.work.stop import StopSignal
from scenesort.backend.work.store import Store
from scenesort.backend.work.worker import DeviceWorker


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


@dataclass
class Service:
    """One store, one device worker, one job manager, and the signals of the requests
    whose work is in flight (so that a shutdown can stop them)."""

    settings: Settings
    store: Store
    worker: DeviceWorker
    jobs: JobManager
    live: set[StopSignal] = field(default_factory=set)

    @classmethod
    def start(cls, settings: Settings) -> Service:
        """A service with its worker thread running."""
        worker = DeviceWorker(settings.device)
        jobs = JobManager(worker, result_bytes=settings.result_bytes,
                          max_seconds=settings.max_seconds)
        return cls(settings, Store(settings.cache_bytes), worker, jobs)

    def deadline(self) -> StopSignal:
        """The stop signal of a request's work, with the deadline --max-seconds gives."""
        return StopSignal(deadline=time.monotonic() + self.settings.max_seconds)

    def scene(self, scene_id: str) -> Any:
        """The scene, mesh or instance list stored under `scene_id`; 404 if none."""
        return _found(self.store.get(scene_id), "scene_id",
                      f"no scene {scene_id} on this service (or evicted)",
                      "upload it with POST /v1/scenes first", "unknown_scene")

    def job(self, job_id: str) -> Job:
        """The job `job_id`; 404 if unknown."""
        return _found(self.jobs.get(job_id), "job_id",
                      f"no job {job_id} (unknown, or finished long ago)",
                      "create a job with POST /v1/jobs", "unknown_job")

    def stop_work(self) -> None:
        """Cancel every job and running request (SIGTERM/SIGINT): they end at their next
        round, and queued ones never start."""
        self.jobs.cancel_all(SHUTDOWN)
        for signal in list(self.live):
            signal.stop(SHUTDOWN)


def _found(value: Any, parameter: str, message: str, fix: str, code: str) -> Any:
    """`value`, or a 404 naming `parameter` when there is none."""
    if value is None:
        raise ApiError(404, parameter, message, fix, code)
    return value


def service(request: Request) -> Service:
    return request.app.state.service


Shared = Annotated[Service, Depends(service)]
