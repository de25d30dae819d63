"""Many clients at once, and clients that leave early: all served, service stays healthy.

The clients that leave do so at a moment the test holds: mid-upload, or while their work is
running in the engine (the service in this process with a gated engine, gated.py)."""

from __future__ import annotations

import logging
import socket
from concurrent.futures import ThreadPoolExecutor

import httpx
import numpy as np
import pytest

from scenesort import kernels
from tests.waiting import until

OCTET = {"Content-Type": "application/octet-stream"}


@pytest.fixture(scope="module")
def scene_id(api, box_scene) -> str:
    response = api.upload(*box_scene)
    assert response.status_code in (200, 201), response.text
    sid = response.json()["scene_id"]
    assert api.client.post(f"/v1/scenes/{sid}/bvh", json={}).status_code == 200
    return sid


def test_eight_concurrent_clients_all_get_their_own_answer(
    service, api, box_scene, scene_id, make_rays
):
    def client_session(k: int) -> np.ndarray:
        origins, directions = make_rays(64 + 16 * k, seed=100 + k)
        body = np.concatenate([origins, directions], axis=1).astype("<f4").tobytes()
        with httpx.Client(base_url=service.url, timeout=120, headers=service.auth) as client:
            upload = client.post(
                "/v1/scenes",
                params={"vertices": len(box_scene[0]), "triangles": len(box_scene[1])},
                content=box_scene[0].tobytes() + box_scene[1].tobytes(),
                headers=OCTET,
            )
            assert upload.status_code in (200, 201) and upload.json()["scene_id"] == scene_id
            response = client.post(
                f"/v1/scenes/{scene_id}/ao",
                params={"rays": len(origins), "spp": 4, "seed": k},
                content=body,
                headers=OCTET,
            )
            assert response.status_code == 200, response.text
            return np.frombuffer(response.content, "<f4")

    with ThreadPoolExecutor(8) as pool:
        results = list(pool.map(client_session, range(8)))
    bvh = kernels.build_bvh(*box_scene, device="cpu")
    for k, got in enumerate(results):
        origins, directions = make_rays(64 + 16 * k, seed=100 + k)
        expected = kernels.ambient_occlusion(bvh, origins, directions, spp=4, seed=k)
        np.testing.assert_array_equal(got, np.asarray(expected, np.float32))
    assert api.health().status_code == 200


def test_a_client_that_hangs_up_mid_render_stops_the_work(
    inproc, gate, box_scene, make_rays, caplog
) -> None:
    """The request's work is provably running (the engine holds it before its first
    round) when its client hangs up: the service notices, stops the work at that round
    without rendering, answers nobody (a 400 in its log), frees the worker and answers the
    next client exactly (end to end with the real engine: test_hostile.py)."""
    caplog.set_level(logging.INFO, logger="scenesort")
    scene_id = upload(inproc.client, box_scene)
    origins, directions = make_rays(4000, seed=5)
    sock = raw_post(inproc, f"/v1/scenes/{scene_id}/ao?rays=4000&spp=256",
                    np.concatenate([origins, directions], axis=1).astype("<f4").tobytes())
    gate.wait_entered()
    [signal] = inproc.service.live  # the running request's stop signal
    sock.close()
    until(lambda: signal.stopped, "the service to notice the hang-up")
    assert signal.reason == "the client disconnected"
    gate.release()
    inproc.wait_idle()
    assert (gate.passed, gate.rounds) == (1, 0)  # stopped at the round: nothing rendered
    until(lambda: "work stopped early: the client disconnected" in caplog.text
          and "ao?rays=4000&spp=256 -> 400" in caplog.text, "the log to say both")
    assert not inproc.service.live
    answers_the_next_client(inproc.client, scene_id, box_scene, make_rays)


def test_a_client_that_hangs_up_mid_upload_never_reaches_the_worker(
    inproc, gate, box_scene, make_rays, caplog
) -> None:
    """Half of the rays sent, then the connection closed: the request ends while reading
    (a 400 in the log) and no work is queued or run."""
    caplog.set_level(logging.INFO, logger="scenesort")
    scene_id = upload(inproc.client, box_scene)
    origins, directions = make_rays(4000, seed=5)
    body = np.concatenate([origins, directions], axis=1).astype("<f4").tobytes()
    raw_post(inproc, f"/v1/scenes/{scene_id}/ao?rays=4000&spp=7", body, len(body) // 2).close()
    until(lambda: "ao?rays=4000&spp=7 -> 400" in caplog.text, "the request to end")
    assert gate.calls == 0 and inproc.service.worker.queued == 0
    gate.release()
    answers_the_next_client(inproc.client, scene_id, box_scene, make_rays)


def upload(client: httpx.Client, scene: tuple[np.ndarray, np.ndarray]) -> str:
    v, i = scene
    response = client.post("/v1/scenes", params={"vertices": len(v), "triangles": len(i)},
                           content=v.tobytes() + i.tobytes(), headers=OCTET)
    assert response.status_code in (200, 201), response.text
    return response.json()["scene_id"]


def raw_post(inproc, path: str, body: bytes, send: int | None = None) -> socket.socket:
    """A POST of `body` (its first `send` bytes only, if given) on a raw socket."""
    host, port = inproc.host_port()
    sock = socket.create_connection((host, port), timeout=10)
    sock.sendall(f"POST {path} HTTP/1.1\r\nHost: {host}:{port}\r\nContent-Type: "
                 f"application/octet-stream\r\nContent-Length: {len(body)}\r\n\r\n".encode()
                 + body[:send])
    return sock


def answers_the_next_client(client: httpx.Client, scene_id: str, box_scene, make_rays) -> None:
    """Health, and a small request answered exactly as the engine answers it."""
    assert client.get("/v1/health").status_code == 200
    small_o, small_d = make_rays(50, seed=6)
    response = client.post(f"/v1/scenes/{scene_id}/ao", params={"rays": 50, "spp": 2, "seed": 1},
                           content=np.concatenate([small_o, small_d], axis=1).astype("<f4")
                           .tobytes(), headers=OCTET)
    assert response.status_code == 200, response.text
    bvh = kernels.build_bvh(*box_scene, device="cpu")
    expected = kernels.ambient_occlusion(bvh, small_o, small_d, spp=2, seed=1)
    np.testing.assert_array_equal(np.frombuffer(response.content, "<f4"), expected)
