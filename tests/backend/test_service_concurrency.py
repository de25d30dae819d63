"""Many clients at once, and clients that leave early: all served, service stays healthy."""

from __future__ import annotations

import socket
import time
from concurrent.futures import ThreadPoolExecutor
from urllib.parse import urlsplit

import httpx
import numpy as np
import pytest

from scenesort import kernels

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


def _send_and_hang_up(url: str, path: str, body: bytes, send_all: bool) -> None:
    """Send a request over a raw socket and close it without reading the answer."""
    parts = urlsplit(url)
    head = (
        f"POST {path} HTTP/1.1\r\nHost: {parts.netloc}\r\n"
        f"Content-Type: application/octet-stream\r\nContent-Length: {len(body)}\r\n\r\n"
    ).encode()
    with socket.create_connection((parts.hostname, parts.port), timeout=10) as sock:
        sock.sendall(head + (body if send_all else body[: len(body) // 2]))
        time.sleep(0.3)  # the service is now reading or rendering


def test_client_leaving_mid_render_leaves_the_service_healthy(
    service, api, box_scene, scene_id, make_rays
):
    origins, directions = make_rays(4000, seed=5)
    heavy = np.concatenate([origins, directions], axis=1).astype("<f4").tobytes()
    path = f"/v1/scenes/{scene_id}/ao?rays=4000&spp=256"
    _send_and_hang_up(service.url, path, heavy, send_all=True)  # leaves mid-render
    _send_and_hang_up(service.url, path, heavy, send_all=False)  # leaves mid-upload
    assert api.health().status_code == 200  # the event loop is free while the worker renders
    small_o, small_d = make_rays(50, seed=6)
    response = api.ao(scene_id, small_o, small_d, spp=2, seed=1)
    assert response.status_code == 200, response.text
    bvh = kernels.build_bvh(*box_scene, device="cpu")
    expected = kernels.ambient_occlusion(bvh, small_o, small_d, spp=2, seed=1)
    np.testing.assert_array_equal(np.frombuffer(response.content, "<f4"), expected)
    assert service.proc.poll() is None
    assert " -> 500 " not in service.log()
