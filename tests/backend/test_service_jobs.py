"""Camera render jobs: create, poll, events, result (float32 and PNG), cancel."""

from __future__ import annotations

import io
import json
import time

import httpx
import numpy as np
import pytest
from PIL import Image

import kernels
from kernels import Camera

POLL_LIMIT_S = 120.0


def camera(width: int, height: int) -> dict:
    cam = Camera.look_at((0.2, 2.0, 1.5), (0.0, 0.0, 0.0), (0, 1, 0), 50.0, width, height)
    return cam.to_dict()


@pytest.fixture(scope="module")
def scene_id(api, box_scene) -> str:
    response = api.upload(*box_scene)
    assert response.status_code in (200, 201), response.text
    return response.json()["scene_id"]


def wait(api, job_id: str, states: set[str]) -> dict:
    """Poll the job until its state is in `states` (bounded in time and count)."""
    deadline = time.monotonic() + POLL_LIMIT_S
    for _ in range(int(POLL_LIMIT_S / 0.05)):
        status = api.client.get(f"/v1/jobs/{job_id}").json()
        if status["state"] in states or time.monotonic() > deadline:
            return status
        time.sleep(0.05)
    return status


def create(api, scene_id: str, width: int, height: int, **params) -> dict:
    body = {"scene_id": scene_id, "camera": camera(width, height), **params}
    response = api.client.post("/v1/jobs", json=body)
    assert response.status_code == 202, response.text
    return response.json()


def test_job_renders_what_the_direct_call_renders(api, box_scene, scene_id) -> None:
    job = create(api, scene_id, 40, 30, spp=4, seed=2)
    assert job["state"] in ("queued", "running") and (job["width"], job["height"]) == (40, 30)
    status = wait(api, job["job_id"], {"done", "failed", "cancelled"})
    assert status["state"] == "done", status
    assert status["progress"] == 1.0
    assert {"bvh", "camera", "ao", "png", "total"} <= set(status["timings_ms"])
    raw = api.client.get(f"/v1/jobs/{job['job_id']}/result", params={"format": "f32"})
    assert raw.status_code == 200 and raw.headers["x-width"] == "40"
    got = np.frombuffer(raw.content, "<f4").reshape(30, 40)
    origins, directions, tmin, tmax = Camera.from_dict(camera(40, 30)).rays()
    bvh = kernels.build_bvh(*box_scene, device="cpu")
    expected = kernels.render_ao(bvh, origins, directions, spp=4, seed=2, tmin=tmin, tmax=tmax).ao
    np.testing.assert_array_equal(got.ravel(), np.asarray(expected, np.float32))
    png = api.client.get(f"/v1/jobs/{job['job_id']}/result", params={"format": "png"})
    image = Image.open(io.BytesIO(png.content))
    assert png.headers["content-type"] == "image/png"
    assert image.size == (40, 30) and image.mode == "L"
    expected_png = np.round(np.clip(got, 0, 1) * 255).astype(np.uint8)
    np.testing.assert_array_equal(np.asarray(image), expected_png)


def test_events_stream_progress_until_the_end(api, service, scene_id) -> None:
    job = create(api, scene_id, 64, 48, spp=16, seed=1)
    events: list[tuple[str, dict]] = []
    with httpx.stream(
        "GET", f"{service.url}/v1/jobs/{job['job_id']}/events", timeout=POLL_LIMIT_S
    ) as stream:
        assert stream.headers["content-type"].startswith("text/event-stream")
        name = None
        for line in stream.iter_lines():
            if line.startswith("event: "):
                name = line[len("event: ") :]
            elif line.startswith("data: "):
                events.append((name or "", json.loads(line[len("data: ") :])))
                if name == "end" or len(events) > 10_000:
                    break
    assert events[-1][0] == "end" and events[-1][1]["state"] == "done"
    progress = [data["progress"] for _, data in events]
    assert progress == sorted(progress) and progress[-1] == 1.0
    assert all(name == "progress" for name, _ in events[:-1])


def test_result_before_done_is_409(api, scene_id) -> None:
    job = create(api, scene_id, 256, 192, spp=64)
    early = api.client.get(f"/v1/jobs/{job['job_id']}/result")
    api.client.delete(f"/v1/jobs/{job['job_id']}")
    assert early.status_code == 409 and early.json()["parameter"] == "job_id"
    wait(api, job["job_id"], {"done", "failed", "cancelled"})


def test_a_cancelled_job_stops_and_the_worker_goes_on(api, scene_id) -> None:
    big = create(api, scene_id, 256, 192, spp=256)  # minutes of work if it were not stopped
    queued = create(api, scene_id, 16, 12, spp=1)
    running = wait(api, big["job_id"], {"running", "done", "failed", "cancelled"})
    assert running["state"] == "running"
    # Cancelling a queued job ends it at once; it never starts.
    assert api.client.delete(f"/v1/jobs/{queued['job_id']}").json()["state"] == "cancelled"
    cancel = api.client.delete(f"/v1/jobs/{big['job_id']}")
    assert cancel.status_code == 200
    stopped = wait(api, big["job_id"], {"cancelled", "done", "failed"})
    assert stopped["state"] == "cancelled" and stopped["progress"] < 1.0
    later = api.client.get(f"/v1/jobs/{big['job_id']}").json()
    assert later["progress"] == stopped["progress"]  # nothing moves after the stop
    assert api.client.get(f"/v1/jobs/{queued['job_id']}").json()["state"] == "cancelled"
    small = create(api, scene_id, 16, 12, spp=1)
    assert wait(api, small["job_id"], {"done", "failed", "cancelled"})["state"] == "done"
