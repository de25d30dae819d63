"""Jobs and AO requests while they are provably queued or running: the service in this
process with its engine held before the first round (tests/backend/gated.py), so the test,
not the machine's speed, decides what happens first.

Each behaviour also has an end-to-end test against a `scenesort serve` process with the real
engine, named in its docstring.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import json
import socket

import httpx
import pytest
from gated import GatedEngine, Running
from scenesort.kernels import Camera
from service_client import OCTET, floor_and_box, ray_body, rays_towards_floor, scene_body

from tests.waiting import WAIT_S, until


@pytest.fixture(scope="module")
def scene_id(inproc: Running) -> str:
    v, i = floor_and_box()
    response = inproc.client.post("/v1/scenes", params={"vertices": len(v), "triangles": len(i)},
                                  content=scene_body(v, i), headers=OCTET)
    assert response.status_code in (200, 201), response.text
    return response.json()["scene_id"]


def create(inproc: Running, scene_id: str) -> str:
    """A 16x12 job at 1 spp; its id."""
    cam = Camera.look_at((0.2, 2.0, 1.5), (0, 0, 0), (0, 1, 0), 50.0, 16, 12).to_dict()
    response = inproc.client.post("/v1/jobs", json={"scene_id": scene_id, "camera": cam,
                                                    "spp": 1})
    assert response.status_code == 202, response.text
    return response.json()["job_id"]


def finish(inproc: Running, job_id: str) -> dict:
    """The job's status once its task on the worker has ended (run or stopped) or was
    dropped from the queue (a cancelled future: final already)."""
    job = inproc.service.jobs.get(job_id)
    assert job is not None and job.future is not None
    if not job.future.cancelled():
        with contextlib.suppress(concurrent.futures.CancelledError):
            job.future.result(timeout=WAIT_S)
    return inproc.client.get(f"/v1/jobs/{job_id}").json()


def test_a_job_has_no_result_until_it_is_done(inproc: Running, gate: GatedEngine,
                                              scene_id: str) -> None:
    """409 naming the job while it runs, the image once done (end to end:
    test_service_jobs.py, a cancelled job's result)."""
    job_id = create(inproc, scene_id)
    gate.wait_entered()
    early = inproc.client.get(f"/v1/jobs/{job_id}/result")
    assert early.status_code == 409 and early.json()["parameter"] == "job_id"
    assert f"job {job_id} is running" in early.json()["detail"]
    gate.release()
    assert finish(inproc, job_id)["state"] == "done"
    result = inproc.client.get(f"/v1/jobs/{job_id}/result")
    assert result.status_code == 200 and len(result.content) == 4 * 16 * 12


def test_cancel_stops_a_running_job_at_its_next_round_and_a_queued_one_never_starts(
    inproc: Running, gate: GatedEngine, scene_id: str
) -> None:
    """(End to end: test_service_jobs.py::test_a_cancelled_job_stops_and_the_worker_goes_on.)"""
    running = create(inproc, scene_id)
    assert gate.wait_entered() == 1
    queued = create(inproc, scene_id)
    assert inproc.service.worker.queued == 1
    assert inproc.client.delete(f"/v1/jobs/{queued}").json()["state"] == "cancelled"
    assert inproc.service.worker.queued == 0  # its place in the queue is free at once
    # A running job is told to stop; it does at its next round, which the gate holds back.
    assert inproc.client.delete(f"/v1/jobs/{running}").json()["state"] == "running"
    gate.release()
    stopped = finish(inproc, running)
    assert stopped["state"] == "cancelled" and stopped["error"] == "cancelled by the client"
    assert stopped["progress"] < 1.0
    assert finish(inproc, queued)["state"] == "cancelled"
    assert (gate.calls, gate.rounds) == (1, 0)  # the queued job never reached the engine
    after = create(inproc, scene_id)  # the worker goes on
    assert finish(inproc, after)["state"] == "done" and gate.rounds == 1


def test_event_streams_on_a_running_job_are_capped_and_freed_when_closed(
    inproc: Running, gate: GatedEngine, scene_id: str
) -> None:
    """Four streams per job (Settings.max_streams_per_job); the fifth and later get 429 with
    Retry-After; closed ones free their places (end to end: test_hostile.py)."""
    job_id = create(inproc, scene_id)
    gate.wait_entered()
    url = f"{inproc.url}/v1/jobs/{job_id}/events"
    with contextlib.ExitStack() as streams:
        answers = [streams.enter_context(httpx.stream("GET", url, timeout=WAIT_S))
                   for _ in range(6)]
        assert [a.status_code for a in answers] == [200] * 4 + [429] * 2
        assert all(a.headers["retry-after"] for a in answers[4:])
    job = inproc.service.jobs.get(job_id)
    until(lambda: job.streams == 0, "the service to release the closed streams")
    with httpx.stream("GET", url, timeout=WAIT_S) as again:
        assert again.status_code == 200
        data = (json.loads(line[len("data: "):]) for line in again.iter_lines()
                if line.startswith("data: "))
        assert next(data)["state"] == "running"  # sent while the engine holds the job
        gate.release()
        assert list(data)[-1]["state"] == "done"


def send_ao(inproc: Running, scene_id: str, rays: int) -> socket.socket:
    """An AO request sent whole over a raw socket whose answer is never read."""
    body = ray_body(*rays_towards_floor(rays))
    host, port = inproc.host_port()
    sock = socket.create_connection((host, port), timeout=WAIT_S)
    sock.sendall((f"POST /v1/scenes/{scene_id}/ao?rays={rays}&spp=1 HTTP/1.1\r\n"
                  f"Host: {host}:{port}\r\nContent-Type: application/octet-stream\r\n"
                  f"Content-Length: {len(body)}\r\n\r\n").encode() + body)
    return sock


def test_ao_requests_whose_clients_hang_up_while_queued_never_run(
    inproc: Running, gate: GatedEngine, scene_id: str
) -> None:
    """Eight requests queued behind a running job, all hung up on: each leaves the queue
    without running, and the worker goes on (end to end: test_hostile.py)."""
    holder = create(inproc, scene_id)
    gate.wait_entered()
    sockets = [send_ao(inproc, scene_id, 64) for _ in range(8)]
    until(lambda: inproc.service.worker.queued == 8, "the eight requests to be queued")
    for sock in sockets:
        sock.close()
    until(lambda: inproc.service.worker.queued == 0, "the hung-up requests to leave the queue")
    gate.release()
    assert finish(inproc, holder)["state"] == "done"
    inproc.wait_idle()
    assert gate.calls == 1  # only the job ever reached the engine
    ok = inproc.client.post(f"/v1/scenes/{scene_id}/ao", params={"rays": 16, "spp": 1},
                            content=ray_body(*rays_towards_floor(16)), headers=OCTET)
    assert ok.status_code == 200 and len(ok.content) == 64
