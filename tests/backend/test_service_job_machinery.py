"""The device worker and job records (backend/work/) with plain work functions."""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import json
import threading

import numpy as np
import pytest
from scenesort.backend.work.jobs import Job, JobManager, job_events
from scenesort.backend.work.worker import DeviceWorker, QueueFull

WAIT_S = 30.0  # bound on every wait below; none should come close


def wait_final(job: Job) -> str:
    """The job's state once its task on the worker has ended, or at once if it was dropped
    from the queue (a cancelled future never runs, so there is nothing to wait for)."""
    assert job.future is not None
    if not job.future.cancelled():
        with contextlib.suppress(concurrent.futures.CancelledError):
            job.future.result(timeout=WAIT_S)
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
    """The job reports its first step, then waits for the test: cancelled there, it stops
    at its next report; the job queued behind it never runs."""
    manager = JobManager(worker)
    first_step, go_on, steps = threading.Event(), threading.Event(), []

    def long(job: Job) -> None:
        for step in range(3):
            job.report("ao", step / 3)  # raises once cancel is asked
            steps.append(step)
            first_step.set()
            assert go_on.wait(WAIT_S)

    job = manager.create("s", 1, 1, long)
    queued = manager.create("s", 1, 1, lambda job: steps.append(-1))
    assert first_step.wait(WAIT_S)
    manager.cancel(queued.job_id)
    manager.cancel(job.job_id)
    assert job.state == "running"  # told to stop; it does at its next report
    go_on.set()
    assert wait_final(job) == "cancelled" and wait_final(queued) == "cancelled"
    assert steps == [0]  # one step, and the queued job never ran
    assert job.progress == 0.0 and job.error == "cancelled by the client"


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
    """Cancel at every moment around the worker's start: each job ends cancelled or done,
    and a cancelled job never reports progress afterwards. Whatever the interleaving, the
    outcome must be one of the two; the ends of the range are held, not hoped for: every
    fifth job is cancelled while the worker is provably busy (so it never starts), the next
    once it has provably reported (so it runs to its end)."""
    manager = JobManager(worker)
    finals = []
    for k in range(200):
        reported: list[None] = []
        busy, free, ran = threading.Event(), threading.Event(), threading.Event()
        if k % 5 == 0:  # the worker busy: the job is still queued when cancelled
            worker.submit(lambda b=busy, f=free: b.set() or f.wait(WAIT_S))
            assert busy.wait(WAIT_S)

        def work(job: Job, r: list = reported, ran: threading.Event = ran) -> None:
            r.append(job.report("ao", 0.5))
            ran.set()

        job = manager.create("s", 1, 1, work)
        if k % 5 == 1:  # reported already: the cancel comes too late to stop it
            assert ran.wait(WAIT_S)
        manager.cancel(job.job_id)  # otherwise: anywhere around the worker's start
        free.set()
        finals.append(wait_final(job))
        assert reported == ([] if finals[-1] == "cancelled" else [None])
        assert job.snapshot()["state"] == finals[-1]  # final states stay final
        if k % 5 in (0, 1):
            assert finals[-1] == ("cancelled" if k % 5 == 0 else "done")
    assert set(finals) == {"cancelled", "done"}


def test_events_end_with_the_final_state(worker) -> None:
    """Each step waits until the stream has sent it: every step is seen, in order, as a
    `progress` event, then the final state as `end`."""
    manager = JobManager(worker)
    seen = [threading.Event() for _ in range(3)]

    def steps(job: Job) -> None:
        for k in range(3):
            job.report("ao", (k + 1) / 4)
            assert seen[k].wait(WAIT_S)

    job = manager.create("s", 1, 1, steps)

    async def collect() -> list[str]:
        async def connected() -> bool:
            return False

        events = []
        async for event in job_events(job, connected, poll_s=0.01):
            events.append(event)
            progress = json.loads(event.split("data: ")[1])["progress"]
            for k in range(3):
                if progress == (k + 1) / 4:
                    seen[k].set()
        return events

    events = asyncio.run(asyncio.wait_for(collect(), WAIT_S))
    names = [e.split("\n")[0] for e in events]
    assert names[-1] == "event: end" and set(names[:-1]) == {"event: progress"}
    progress = [json.loads(e.split("data: ")[1])["progress"] for e in events[:-1]]
    assert [p for p in progress if p > 0] == [0.25, 0.5, 0.75]
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
