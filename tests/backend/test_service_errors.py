"""Bad requests: each is a 4xx JSON error naming the parameter and a fix; never a 5xx."""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import pytest

GOOD_V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
GOOD_I = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
OCTET = {"Content-Type": "application/octet-stream"}
UNKNOWN = "0" * 32


def scene(v: np.ndarray = GOOD_V, i: np.ndarray = GOOD_I) -> bytes:
    return v.astype("<f4").tobytes() + i.astype("<i4").tobytes()


def with_vertex(value: float) -> bytes:
    v = GOOD_V.copy()
    v[2, 1] = value
    return scene(v)


def with_index(value: int) -> bytes:
    i = GOOD_I.copy()
    i[1, 2] = value
    return scene(GOOD_V, i)


def rays(directions: list[list[float]], origin: float = 0.5) -> bytes:
    d = np.array(directions, np.float32)
    o = np.full_like(d, origin)
    return np.concatenate([o, d], axis=1).astype("<f4").tobytes()


ONE_RAY = rays([[0, 0, -1]])
SC = "/v1/scenes"
CAMERA = {"matrix_world": np.eye(4).tolist(), "width": 8, "height": 6}

# (id, method, path ("{sid}" = a known scene), query, body, headers, status, parameter)
CASES: list[tuple[str, str, str, dict, Any, dict, int, str]] = [
    ("no vertices", "POST", SC, {"triangles": 2}, scene(), OCTET, 422, "vertices"),
    ("no triangles", "POST", SC, {"vertices": 4}, scene(), OCTET, 422, "triangles"),
    (
        "vertices not int",
        "POST",
        SC,
        {"vertices": "four", "triangles": 2},
        scene(),
        OCTET,
        422,
        "vertices",
    ),
    ("zero vertices", "POST", SC, {"vertices": 0, "triangles": 2}, scene(), OCTET, 422, "vertices"),
    (
        "negative triangles",
        "POST",
        SC,
        {"vertices": 4, "triangles": -1},
        scene(),
        OCTET,
        422,
        "triangles",
    ),
    ("body short", "POST", SC, {"vertices": 5, "triangles": 2}, scene(), OCTET, 400, "body"),
    ("body long", "POST", SC, {"vertices": 4, "triangles": 1}, scene(), OCTET, 400, "body"),
    ("empty body", "POST", SC, {"vertices": 4, "triangles": 2}, b"", OCTET, 400, "body"),
    (
        "NaN vertex",
        "POST",
        SC,
        {"vertices": 4, "triangles": 2},
        with_vertex(np.nan),
        OCTET,
        400,
        "vertices",
    ),
    (
        "Inf vertex",
        "POST",
        SC,
        {"vertices": 4, "triangles": 2},
        with_vertex(np.inf),
        OCTET,
        400,
        "vertices",
    ),
    (
        "index too big",
        "POST",
        SC,
        {"vertices": 4, "triangles": 2},
        with_index(4),
        OCTET,
        400,
        "indices",
    ),
    (
        "negative index",
        "POST",
        SC,
        {"vertices": 4, "triangles": 2},
        with_index(-1),
        OCTET,
        400,
        "indices",
    ),
    (
        "json content type",
        "POST",
        SC,
        {"vertices": 4, "triangles": 2},
        scene(),
        {"Content-Type": "application/json"},
        415,
        "Content-Type",
    ),
    ("bad scene id", "GET", f"{SC}/not-a-hash", {}, None, {}, 422, "scene_id"),
    ("unknown scene", "GET", f"{SC}/{UNKNOWN}", {}, None, {}, 404, "scene_id"),
    (
        "bvh unknown scene",
        "POST",
        f"{SC}/{UNKNOWN}/bvh",
        {},
        {"method": "sah"},
        {},
        404,
        "scene_id",
    ),
    (
        "bvh unknown method",
        "POST",
        f"{SC}/{{sid}}/bvh",
        {},
        {"method": "octree"},
        {},
        422,
        "method",
    ),
    ("bvh leaf size 0", "POST", f"{SC}/{{sid}}/bvh", {}, {"leaf_size": 0}, {}, 422, "leaf_size"),
    (
        "bvh leaf size text",
        "POST",
        f"{SC}/{{sid}}/bvh",
        {},
        {"leaf_size": "big"},
        {},
        422,
        "leaf_size",
    ),
    ("bvh extra field", "POST", f"{SC}/{{sid}}/bvh", {}, {"levels": 3}, {}, 422, "levels"),
    (
        "bvh invalid json",
        "POST",
        f"{SC}/{{sid}}/bvh",
        {},
        b"{method: sah",
        {"Content-Type": "application/json"},
        400,
        "body",
    ),
    ("ao no rays count", "POST", f"{SC}/{{sid}}/ao", {}, ONE_RAY, OCTET, 422, "rays"),
    ("ao count mismatch", "POST", f"{SC}/{{sid}}/ao", {"rays": 2}, ONE_RAY, OCTET, 400, "body"),
    ("ao spp 0", "POST", f"{SC}/{{sid}}/ao", {"rays": 1, "spp": 0}, ONE_RAY, OCTET, 422, "spp"),
    (
        "ao negative distance",
        "POST",
        f"{SC}/{{sid}}/ao",
        {"rays": 1, "distance": -1.0},
        ONE_RAY,
        OCTET,
        422,
        "distance",
    ),
    (
        "ao NaN distance",
        "POST",
        f"{SC}/{{sid}}/ao",
        {"rays": 1, "distance": "nan"},
        ONE_RAY,
        OCTET,
        422,
        "distance",
    ),
    (
        "ao target error 0",
        "POST",
        f"{SC}/{{sid}}/ao",
        {"rays": 1, "target_error": 0},
        ONE_RAY,
        OCTET,
        422,
        "target_error",
    ),
    (
        "ao max pixel error 1",
        "POST",
        f"{SC}/{{sid}}/ao",
        {"rays": 1, "max_pixel_error": 1},
        ONE_RAY,
        OCTET,
        422,
        "max_pixel_error",
    ),
    (
        "ao adaptive spp over the cap",
        "POST",
        f"{SC}/{{sid}}/ao",
        {"rays": 1, "spp": 2000, "target_error": 0.1},
        ONE_RAY,
        OCTET,
        422,
        "spp",
    ),
    (
        "ao unknown engine",
        "POST",
        f"{SC}/{{sid}}/ao",
        {"rays": 1, "engine": "embree"},
        ONE_RAY,
        OCTET,
        422,
        "engine",
    ),
    (
        "ao zero direction",
        "POST",
        f"{SC}/{{sid}}/ao",
        {"rays": 2},
        rays([[0, 0, -1], [0, 0, 0]]),
        OCTET,
        400,
        "rays",
    ),
    (
        "ao NaN ray",
        "POST",
        f"{SC}/{{sid}}/ao",
        {"rays": 1},
        rays([[0, np.nan, -1]]),
        OCTET,
        400,
        "rays",
    ),
    (
        "ao Inf origin",
        "POST",
        f"{SC}/{{sid}}/ao",
        {"rays": 1},
        rays([[0, 0, -1]], np.inf),
        OCTET,
        400,
        "rays",
    ),
    (
        "ao unknown scene",
        "POST",
        f"{SC}/{UNKNOWN}/ao",
        {"rays": 1},
        ONE_RAY,
        OCTET,
        404,
        "scene_id",
    ),
    ("job unknown", "GET", "/v1/jobs/0123456789abcdef", {}, None, {}, 404, "job_id"),
    ("job result unknown", "GET", "/v1/jobs/0123456789abcdef/result", {}, None, {}, 404, "job_id"),
    ("job no camera", "POST", "/v1/jobs", {}, {"scene_id": "{sid}"}, {}, 422, "camera"),
    (
        "job singular camera",
        "POST",
        "/v1/jobs",
        {},
        {"scene_id": "{sid}", "camera": {**CAMERA, "matrix_world": np.zeros((4, 4)).tolist()}},
        {},
        422,
        "camera",
    ),
    (
        "job camera width 0",
        "POST",
        "/v1/jobs",
        {},
        {"scene_id": "{sid}", "camera": {**CAMERA, "width": 0}},
        {},
        422,
        "camera.width",
    ),
    (
        "job unknown scene",
        "POST",
        "/v1/jobs",
        {},
        {"scene_id": UNKNOWN, "camera": CAMERA},
        {},
        404,
        "scene_id",
    ),
    ("job depth of field focused at 0", "POST", "/v1/jobs", {},
     {"scene_id": "{sid}", "camera": {**CAMERA, "type": "ORTHO", "aperture_size": 0.1,
                                      "focus_distance": 0.0}}, {}, 422, "camera"),
    ("job aperture blades over 16", "POST", "/v1/jobs", {},
     {"scene_id": "{sid}", "camera": {**CAMERA, "aperture_blades": 17}}, {}, 422,
     "aperture_blades"),
    ("job unknown pixel filter", "POST", "/v1/jobs", {},
     {"scene_id": "{sid}", "camera": CAMERA, "pixel_filter": "MITCHELL"}, {}, 422,
     "pixel_filter"),
    ("job filter width over 10", "POST", "/v1/jobs", {},
     {"scene_id": "{sid}", "camera": CAMERA, "filter_width": 10.5}, {}, 422, "filter_width"),
    ("job filter width negative", "POST", "/v1/jobs", {},
     {"scene_id": "{sid}", "camera": CAMERA, "filter_width": -1}, {}, 422, "filter_width"),
    ("unknown route", "GET", "/v1/teapot", {}, None, {}, 404, "path"),
    ("wrong method", "DELETE", "/v1/health", {}, None, {}, 405, "method"),
]


@pytest.fixture(scope="module")
def scene_id(api) -> str:
    response = api.upload(GOOD_V, GOOD_I)
    assert response.status_code in (200, 201), response.text
    return response.json()["scene_id"]


def _fill(value: Any, sid: str) -> Any:
    """Replace the "{sid}" placeholder inside paths and JSON bodies."""
    if isinstance(value, str):
        return value.replace("{sid}", sid)
    if isinstance(value, dict):
        return {k: _fill(v, sid) for k, v in value.items()}
    return value


def test_there_are_at_least_twenty_cases() -> None:
    assert len(CASES) >= 20


@pytest.mark.parametrize(
    ("method", "path", "query", "body", "headers", "status", "parameter"),
    [case[1:] for case in CASES],
    ids=[case[0] for case in CASES],
)
def test_bad_request_is_a_clear_4xx(
    api, scene_id, method, path, query, body, headers, status, parameter
) -> None:
    kwargs: dict[str, Any] = {"params": query, "headers": headers}
    if isinstance(body, bytes):
        kwargs["content"] = body
    elif body is not None:
        kwargs["json"] = _fill(body, scene_id)
    response = api.client.request(method, _fill(path, scene_id), **kwargs)
    assert response.status_code == status, response.text
    assert response.headers["content-type"] == "application/problem+json"
    error = response.json()
    assert set(error) == {"type", "title", "status", "detail", "parameter", "fix"}
    assert error["status"] == status and error["type"].startswith("tag:scenesort,2026:")
    assert parameter in error["parameter"], error
    assert error["detail"] and error["fix"] and error["title"], error


def test_body_over_the_limit_is_413(start_service) -> None:
    """A body over --max-body-mb is refused with 413 naming the option to raise."""
    import httpx

    small = start_service("--max-body-mb", "0.01")  # 10 KiB
    v = np.zeros((1000, 3), np.float32)
    i = np.zeros((10, 3), np.int32)
    response = httpx.post(
        f"{small.url}/v1/scenes",
        params={"vertices": 1000, "triangles": 10},
        content=scene(v, i),
        headers={**OCTET, **small.auth},
        timeout=30,
    )
    assert response.status_code == 413, response.text
    assert "--max-body-mb" in response.json()["fix"]
    assert httpx.get(f"{small.url}/v1/health", timeout=10).status_code == 200


def test_service_healthy_after_bad_requests(api, scene_id, service) -> None:
    for case in CASES:  # again, all at once, then health and a good request
        _, method, path, query, body, headers, _, _ = case
        kwargs: dict[str, Any] = {"params": query, "headers": headers}
        if isinstance(body, bytes):
            kwargs["content"] = body
        elif body is not None:
            kwargs["content"] = json.dumps(_fill(body, scene_id)).encode()
            kwargs["headers"] = {"Content-Type": "application/json"}
        assert api.client.request(method, _fill(path, scene_id), **kwargs).status_code < 500
    assert api.health().status_code == 200
    assert api.client.head(f"/v1/scenes/{scene_id}").status_code == 200
    assert service.proc.poll() is None
    assert "500" not in [line.split(" -> ")[-1][:3] for line in service.log().splitlines()]


def test_dacrt_engine_gives_the_bvh_answer(api, scene_id) -> None:
    """engine=dacrt traces the same rays without the BVH: the same AO, bit for bit."""
    answers = [
        api.client.post(f"/v1/scenes/{scene_id}/ao", params={"rays": 1, "engine": engine},
                        content=ONE_RAY, headers=OCTET)
        for engine in ("bvh", "dacrt")
    ]
    assert [r.status_code for r in answers] == [200, 200], answers[1].text
    assert answers[0].content == answers[1].content and len(answers[0].content) == 4
