"""Scene upload, HEAD probes, content ids and the byte-bounded cache, over real HTTP."""

from __future__ import annotations

import hashlib
import re

import httpx
import numpy as np

from tests.waiting import until


def test_upload_is_201_then_200_with_the_same_id(api, box_scene) -> None:
    vertices, indices = box_scene
    moved = vertices + np.float32(7.0)  # a scene no other test uploads
    first = api.upload(moved, indices)
    second = api.upload(moved, indices)
    assert (first.status_code, second.status_code) == (201, 200), first.text
    assert first.json() == second.json()
    info = first.json()
    assert info["triangles"] == len(indices) and info["vertices"] == len(vertices)
    np.testing.assert_allclose(info["bounds"], [moved.min(0), moved.max(0)])
    assert info["degenerate"] == 0


def test_scene_id_is_what_a_client_computes(api, box_scene) -> None:
    """The add-on hashes its own arrays the documented way and skips the upload."""
    vertices, indices = box_scene
    body = vertices.astype("<f4").tobytes() + indices.astype("<i4").tobytes()
    header = b"scenesort-scene-v1 %d %d\n" % (len(vertices), len(indices))
    client_id = hashlib.sha256(header + body).hexdigest()[:32]
    assert api.upload(vertices, indices).json()["scene_id"] == client_id
    assert api.client.head(f"/v1/scenes/{client_id}").status_code == 200
    assert api.client.get(f"/v1/scenes/{client_id}").json()["scene_id"] == client_id


def test_head_of_an_unknown_scene_is_404(api) -> None:
    assert api.client.head(f"/v1/scenes/{'ab' * 16}").status_code == 404


def test_degenerate_triangles_are_counted(api) -> None:
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0]], np.float32)
    indices = np.array([[0, 1, 2], [0, 1, 3], [1, 1, 2]], np.int32)
    response = api.upload(vertices, indices)
    assert response.status_code in (200, 201)
    assert response.json()["degenerate"] == 2


def test_health_reports_versions_device_and_cache(api) -> None:
    health = api.health().json()
    assert health["status"] == "ok" and health["device"] == "cpu"
    assert health["warp_version"] == "1.19.0"
    assert health["devices"][0] == "cpu"  # then each CUDA device Warp reports
    assert 0 < health["cache"]["bytes"] <= health["cache"]["max_bytes"]
    assert health["max_body_bytes"] == 64 * 2**20  # the shared service's --max-body-mb


def test_cache_evicts_least_recently_used_scene(start_service) -> None:
    """With a 1 KiB cache, three 480-byte scenes cannot all stay: the oldest goes."""
    small = start_service("--cache-mb", str(1024 / 2**20))
    client = httpx.Client(base_url=small.url, timeout=30, headers=small.auth)
    ids = []
    for k in range(3):
        vertices = np.full((20, 3), k, np.float32)  # 240 bytes
        vertices[:, 0] = np.arange(20)
        indices = np.arange(60, dtype=np.int32).reshape(20, 3) % 20  # 240 bytes
        body = vertices.tobytes() + indices.tobytes()
        response = client.post(
            "/v1/scenes",
            params={"vertices": 20, "triangles": 20},
            content=body,
            headers={"Content-Type": "application/octet-stream"},
        )
        assert response.status_code == 201, response.text
        ids.append(response.json()["scene_id"])
        if k == 1:  # touch the first scene: the second becomes least recently used
            assert client.head(f"/v1/scenes/{ids[0]}").status_code == 200
    present = [client.head(f"/v1/scenes/{i}").status_code for i in ids]
    assert present == [200, 404, 200]
    cache = client.get("/v1/health").json()["cache"]
    assert cache["scenes"] == 2 and cache["bytes"] == 960 and cache["evictions"] == 1
    # An unknown scene is a 404 naming the scene, with the fix: upload it again.
    error = client.get(f"/v1/scenes/{ids[1]}").json()
    assert error["parameter"] == "scene_id" and "POST /v1/scenes" in error["fix"]
    client.close()


def test_one_log_line_per_request_with_duration(api, service) -> None:
    marker = "a1" * 16
    for _ in range(3):
        api.client.head(f"/v1/scenes/{marker}")
    def logged() -> list[str]:  # each line is written after its response
        lines = [line for line in service.log().splitlines() if marker in line]
        return lines if len(lines) >= 3 else []

    lines = until(logged, "the three log lines", 5.0)
    assert len(lines) == 3
    assert all(re.search(r"HEAD /v1/scenes/a1\w+ -> 404 in \d+\.\d ms", line) for line in lines)
