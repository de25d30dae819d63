"""The device worker and job records (backend/work/) with plain work functions."""

from __future__ import annotations

import asyncio
import json
import threading

import numpy as np
import pytest
from scenesort.backend.work.jobs import Job, JobManager, job_events
from scenesort.backend.work.worker import DeviceWorker, QueueFull

WAIT_S = 30.0  # bound on every wait below; none should come close


def wait_final(job: Job) -> str:
    for _ in range(int(WAIT_S / 0.01)):
        if job.state in ("done", "failed", "cancelled"):
            return job.state
        threading.Event().wait(0.01)
    return job.state


@pytest.fixture
def worker():
    w = DeviceWorker("cpu", max_queue=4)
    yield w
    w.stop()


def test_work_runs_in_order_on_one_thread(worker) -> None:
    seen: list[tuple[int, str]] = []
    futures = [
        worker.submit(lambda k=k: seen.append((k, threading.current_thread().name)))
        for k in range(4)
    ]
    for f in futures:
        f.result(timeout=WAIT_S)
    assert [k for k, _ in seen] == [0, 1, 2, 3]
    assert {name for _, name in seen} == {"worker-cpu"}


def test_a_full_queue_refuses_instead_of_blocking(worker) -> None:
    gate = threading.Event()
    worker.submit(lambda: gate.wait(WAIT_S))  # occupies the thread
    try:
        with pytest.raises(QueueFull):
            for _ in range(10):
                worker.submit(lambda: None)
    finally:
        gate.set()


def test_errors_fail_the_job_not_the_worker(worker) -> None:
    manager = JobManager(worker)

    def bad_input(job: Job) -> None:
        raise ValueError("spp must be >= 1")

    def bug(job: Job) -> None:
        raise RuntimeError("boom")

    def good(job: Job) -> None:
        job.report("ao", 0.5)
        job.ao = np.zeros((2, 3), np.float32)

    jobs = [manager.create("s", 3, 2, fn) for fn in (bad_input, bug, good)]
    assert [wait_final(j) for j in jobs] == ["failed", "failed", "done"]
    assert jobs[0].error == "invalid input: spp must be >= 1"
    assert jobs[1].error.startswith("internal error: RuntimeError")
    assert jobs[2].progress == 1.0 and "total" in jobs[2].timings_ms


def test_cancel_stops_a_running_job_at_its_next_report(worker) -> None:
    manager = JobManager(worker)
    started, steps = threading.Event(), []

    def long(job: Job) -> None:
        started.set()
        for step in range(10_000):
            job.report("ao", step / 10_000)  # raises once cancel is asked
            steps.append(step)
            threading.Event().wait(0.001)

    job = manager.create("s", 1, 1, long)
    queued = manager.create("s", 1, 1, lambda job: steps.append(-1))
    assert started.wait(WAIT_S)
    manager.cancel(queued.job_id)
    manager.cancel(job.job_id)
    assert wait_final(job) == "cancelled" and wait_final(queued) == "cancelled"
    done_steps = len(steps)
    assert 0 < done_steps < 10_000 and -1 not in steps  # the queued one never ran
    assert job.progress < 1.0


def test_finished_jobs_are_bounded_in_count_and_bytes(worker) -> None:
    manager = JobManager(worker, keep_finished=3, result_bytes=2 * 4000)

    def image(job: Job) -> None:
        job.ao = np.zeros(1000, np.float32)  # 4000 bytes

    jobs = [manager.create("s", 1000, 1, image) for _ in range(4)]
    for job in jobs:
        wait_final(job)
    kept = [j for j in jobs if manager.get(j.job_id) is not None]
    assert kept == jobs[-2:]  # 3 by count, but only 2 images fit in 8000 bytes


def test_cancelled_queued_jobs_free_their_slots(worker) -> None:
    """The queue holds 4: with the thread busy, 20 jobs created and cancelled in turn all
    fit, and none of them runs."""
    manager = JobManager(worker)
    gate, busy, ran = threading.Event(), threading.Event(), []
    worker.submit(lambda: busy.set() or gate.wait(WAIT_S))
    assert busy.wait(WAIT_S)
    try:
        for k in range(20):
            job = manager.create("s", 1, 1, lambda job, k=k: ran.append(k))  # no QueueFull
            manager.cancel(job.job_id)
            assert job.state == "cancelled"
        assert worker.queued == 0
    finally:
        gate.set()
    worker.submit(lambda: None).result(timeout=WAIT_S)
    assert ran == []


def test_a_cancel_racing_the_start_never_ends_running(worker) -> None:
    """Cancel at every moment around the worker's start: each job ends cancelled or
    done, and a cancelled job never reports progress afterwards."""
    manager = JobManager(worker)
    finals = []
    for k in range(200):
        reported: list[None] = []
        job = manager.create("s", 1, 1, lambda job, r=reported: r.append(job.report("ao", 0.5)))
        threading.Event().wait(k % 5 * 1e-4)  # cancel before, around and after the start
        manager.cancel(job.job_id)
        finals.append(wait_final(job))
        assert reported == ([] if finals[-1] == "cancelled" else [None])
        assert job.snapshot()["state"] == finals[-1]  # final states stay final
    assert set(finals) <= {"cancelled", "done"} and "cancelled" in finals


def test_events_end_with_the_final_state(worker) -> None:
    manager = JobManager(worker)

    def steps(job: Job) -> None:
        for k in range(1, 4):
            job.report("ao", k / 4)
            threading.Event().wait(0.1)

    job = manager.create("s", 1, 1, steps)

    async def collect() -> list[str]:
        async def connected() -> bool:
            return False

        return [e async for e in job_events(job, connected, poll_s=0.01)]

    events = asyncio.run(asyncio.wait_for(collect(), WAIT_S))
    names = [e.split("\n")[0] for e in events]
    assert names[-1] == "event: end" and set(names[:-1]) == {"event: progress"}
    last = json.loads(events[-1].split("data: ")[1])
    assert last["state"] == "done" and last["progress"] == 1.0


def test_explicit_ray_ao_stops_between_the_engines_rounds() -> None:
    """The signal reaches the engine's progress calls: stopped (the client hung up) or past
    its deadline, `render.ao.ambient_occlusion` raises Stopped instead of rendering on."""
    from scenesort.backend.render.ao import ambient_occlusion
    from scenesort.backend.wire.binary import SceneArrays
    from scenesort.backend.work.stop import Stopped, StopSignal

    from scenesort import kernels
    from scenesort.ao_options import AoOptions

    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    indices = np.array([[0, 1, 2]], np.int32)
    bvh = kernels.build_bvh(vertices, indices)
    scene = SceneArrays(vertices, indices, scene_id="0" * 32, degenerate=0)
    rays = np.full((8, 3), [0.2, 0.2, 1.0], np.float32), np.tile(np.float32([0, 0, -1]), (8, 1))
    assert ambient_occlusion(bvh, scene, *rays, AoOptions(spp=4), StopSignal())[0].shape == (8,)
    hung_up = StopSignal()
    hung_up.stop("the client disconnected")
    with pytest.raises(Stopped, match="the client disconnected"):
        ambient_occlusion(bvh, scene, *rays, AoOptions(spp=4), hung_up)
    with pytest.raises(Stopped, match="deadline"):
        ambient_occlusion(bvh, scene, *rays, AoOptions(spp=4), StopSignal(deadline=0.0))
