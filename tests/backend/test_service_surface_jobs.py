"""Surface jobs (a bake's texels): AO at explicit points of a scene's triangles as a job,
equal to the engine's `surface_ao`; cancellable; bad points and scenes refused by name."""

from __future__ import annotations

import numpy as np
import pytest
from service_client import job_ended

from scenesort import kernels

POLL_LIMIT_S = 120.0


@pytest.fixture(scope="module")
def scene_id(api, box_scene) -> str:
    response = api.upload(*box_scene)
    assert response.status_code in (200, 201), response.text
    return response.json()["scene_id"]


def _points(triangles: int, count: int, seed: int = 1) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    tri = rng.integers(0, triangles, count).astype(np.int32)
    a, b = rng.random((2, count))
    flip = a + b > 1.0  # fold into the triangle
    a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
    return tri, a.astype(np.float32), b.astype(np.float32)


def _body(tri: np.ndarray, u: np.ndarray, v: np.ndarray) -> bytes:
    return tri.astype("<i4").tobytes() + u.astype("<f4").tobytes() + v.astype("<f4").tobytes()


def _post(api, scene_id: str, texels: tuple[np.ndarray, ...], **params):
    return api.client.post(f"/v1/scenes/{scene_id}/surface-jobs", content=_body(*texels),
                           params={"points": len(texels[0]), **params},
                           headers={"Content-Type": "application/octet-stream"})  # fmt: skip


def test_a_surface_job_gives_surface_aos_numbers(api, box_scene, scene_id) -> None:
    points = _points(len(box_scene[1]), 500)
    response = _post(api, scene_id, points, spp=8, seed=3, distance=0.5)
    assert response.status_code == 202, response.text
    job = response.json()
    assert (job["width"], job["height"]) == (500, 1)
    status = job_ended(api.client, job["job_id"], frozenset({"done", "failed", "cancelled"}),
                       POLL_LIMIT_S)  # fmt: skip
    assert status["state"] == "done", status
    # "ao": the whole trace, what the add-on's info line shows (it read 0.0 ms for bakes)
    assert {"bvh", "ao", "ao.occlusion"} <= set(status["timings_ms"])
    assert status["timings_ms"]["ao"] >= status["timings_ms"]["ao.occlusion"] > 0.0
    raw = api.client.get(f"/v1/jobs/{job['job_id']}/result", params={"format": "f32"})
    got = np.frombuffer(raw.content, "<f4")
    bvh = kernels.build_bvh(*box_scene, device="cpu")
    expected = kernels.surface_ao(bvh, *points, spp=8, seed=3, distance=0.5)
    np.testing.assert_array_equal(got, expected.ao)
    assert status["spp_max"] == 8 and status["rmse_estimate"] == expected.rmse_estimate
    coverage = api.client.get(f"/v1/jobs/{job['job_id']}/result", params={"format": "coverage"})
    assert np.all(np.frombuffer(coverage.content, "<f4") == (expected.spp_used > 0))
    png = api.client.get(f"/v1/jobs/{job['job_id']}/result", params={"format": "png"})
    assert png.status_code == 409  # a surface job makes no picture


def test_a_surface_job_can_be_cancelled(api, box_scene, scene_id) -> None:
    points = _points(len(box_scene[1]), 200_000, seed=2)
    response = _post(api, scene_id, points, spp=1024)
    assert response.status_code == 202, response.text
    job_id = response.json()["job_id"]
    assert api.client.delete(f"/v1/jobs/{job_id}").status_code == 200
    status = job_ended(api.client, job_id, frozenset({"done", "failed", "cancelled"}),
                       POLL_LIMIT_S)  # fmt: skip
    assert status["state"] == "cancelled", status


@pytest.mark.parametrize(("points", "params", "status", "field"), [
    ((np.array([0], np.int32), np.array([0.2], np.float32), np.array([np.nan], np.float32)),
     {}, 400, "body (points)"),
    (None, {"points": 3}, 400, "body"),
    (None, {"engine": "dacrt"}, 422, "engine"),
    (None, {"points": 0}, 422, "points"),
])  # fmt: skip
def test_bad_points_are_refused_by_name(api, scene_id, points, params, status, field) -> None:
    points = points or (np.zeros(2, np.int32), np.full(2, 0.2, np.float32),
                        np.full(2, 0.2, np.float32))  # fmt: skip
    response = _post(api, scene_id, points, **params)
    assert response.status_code == status, response.text
    assert field in response.text


def test_points_off_the_scene_fail_the_job_with_the_engines_reason(api, box_scene,
                                                                   scene_id) -> None:
    tri = np.array([len(box_scene[1])], np.int32)  # one past the last triangle
    response = _post(api, scene_id, (tri, np.full(1, 0.2, np.float32), np.full(1, 0.2, np.float32)))
    status = job_ended(api.client, response.json()["job_id"],
                       frozenset({"done", "failed", "cancelled"}), POLL_LIMIT_S)  # fmt: skip
    assert status["state"] == "failed" and "triangles must lie in" in status["error"]
