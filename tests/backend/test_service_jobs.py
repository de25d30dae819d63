"""Camera render jobs: create, poll, events, result (float32 and PNG), cancel."""

from __future__ import annotations

import io
import json
import time

import httpx
import numpy as np
import pytest
from PIL import Image
from scenesort.kernels import Camera
from service_client import Api, floor_and_box, job_ended

from scenesort import kernels

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
    """The job's status once its state is in `states` (polled; fails past POLL_LIMIT_S)."""
    return job_ended(api.client, job_id, frozenset(states), POLL_LIMIT_S)


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
    assert {"bvh", "camera", "ao", "total"} <= set(status["timings_ms"])
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


def test_a_job_reports_what_it_achieved(api, box_scene, scene_id) -> None:
    """The status carries the render's estimated RMSE, mean and largest spp and rays,
    exactly `AoResult.stats()` of the same render; max_pixel_error reaches the engine."""
    origins, directions, tmin, tmax = Camera.from_dict(camera(40, 30)).rays()
    bvh = kernels.build_bvh(*box_scene, device="cpu")
    for params in ({"spp": 4, "seed": 2, "target_error": 0.05},
                   {"spp": 4, "seed": 2, "max_pixel_error": 0.1}):
        job = create(api, scene_id, 40, 30, **params)
        status = wait(api, job["job_id"], {"done", "failed", "cancelled"})
        assert status["state"] == "done", status
        expected = kernels.render_ao(bvh, origins, directions, tmin=tmin, tmax=tmax,
                                     **params).stats().to_dict()
        got = {k: status[k] for k in ("rmse_estimate", "spp_mean", "spp_max", "rays",
                                      "denoised")}
        assert got == pytest.approx(expected), (got, expected)
        assert status["spp_max"] >= 8 and status["rmse_estimate"] > 0


def test_a_filtered_job_renders_what_render_film_renders(api, box_scene, scene_id) -> None:
    """pixel_filter and filter_width reach the engine: AO and coverage are render_film's
    filtered AO and alpha, sample for sample, and the status names the film."""
    job = create(api, scene_id, 40, 30, spp=8, seed=3, pixel_filter="GAUSSIAN",
                 filter_width=1.5)
    status = wait(api, job["job_id"], {"done", "failed", "cancelled"})
    assert status["state"] == "done", status
    assert status["film"] == "GAUSSIAN 1.5 px"
    bvh = kernels.build_bvh(*box_scene, device="cpu")
    film = kernels.render_film(bvh, Camera.from_dict(camera(40, 30)), spp=8, seed=3,
                               pixel_filter="GAUSSIAN", filter_width=1.5)
    for name, expected in (("f32", film.ao), ("coverage", film.alpha)):
        raw = api.client.get(f"/v1/jobs/{job['job_id']}/result", params={"format": name})
        np.testing.assert_array_equal(np.frombuffer(raw.content, "<f4").reshape(30, 40),
                                      expected)
    assert ((film.alpha > 0) & (film.alpha < 1)).any()  # the box's edges are filtered
    assert (status["spp_mean"], status["spp_max"], status["rays"]) == (8, 8, film.rays)
    assert status["rmse_estimate"] == pytest.approx(film.rmse_estimate)


def test_a_filtered_job_makes_pixel_centre_rays_only_for_its_z_pass(api, scene_id) -> None:
    """The film traces its own camera rays: the pixel centres' (the "camera" phase) are made
    only for the Z pass (and the other passes that need them), not for a viewport's rounds."""
    for depth in (True, False):
        job = create(api, scene_id, 40, 30, spp=2, filter_width=1.5, depth=depth)
        status = wait(api, job["job_id"], {"done", "failed", "cancelled"})
        assert status["state"] == "done", status
        phases = set(status["timings_ms"])
        assert ({"camera", "depth"} <= phases) if depth else not ({"camera", "depth"} & phases)


def test_a_filtered_job_with_an_error_target_is_render_films(api, box_scene, scene_id) -> None:
    """target_error with a filter: the adaptive rounds over the filtered pixels, as
    render_film renders them (image, coverage, spp and the estimate)."""
    params = {"spp": 8, "seed": 2, "target_error": 0.05, "filter_width": 1.5}
    job = create(api, scene_id, 40, 30, **params)
    status = wait(api, job["job_id"], {"done", "failed", "cancelled"})
    assert status["state"] == "done", status
    assert status["film"] == "BLACKMAN_HARRIS 1.5 px"
    bvh = kernels.build_bvh(*box_scene, device="cpu")
    film = kernels.render_film(bvh, Camera.from_dict(camera(40, 30)), **params)
    raw = api.client.get(f"/v1/jobs/{job['job_id']}/result", params={"format": "f32"})
    np.testing.assert_array_equal(np.frombuffer(raw.content, "<f4").reshape(30, 40), film.ao)
    assert status["rmse_estimate"] == pytest.approx(film.rmse_estimate)
    assert (status["spp_mean"], status["spp_max"]) == (pytest.approx(film.spp_mean),
                                                       film.spp_max)
    assert film.spp_max > 8  # the rounds went on past the minimum


def test_a_filter_with_dacrt_renders_pixel_centres_and_says_so(api, scene_id) -> None:
    """DACRT traces pixel centres: a filter asked for with it is not used, and the status's
    film says so (the image is the pixel-centre render's)."""
    plain = create(api, scene_id, 40, 30, spp=8, seed=2, engine="dacrt")
    asked = create(api, scene_id, 40, 30, spp=8, seed=2, engine="dacrt", filter_width=1.5)
    images = []
    for job in (plain, asked):
        status = wait(api, job["job_id"], {"done", "failed", "cancelled"})
        assert status["state"] == "done", status
        raw = api.client.get(f"/v1/jobs/{job['job_id']}/result", params={"format": "f32"})
        images.append(raw.content)
    assert wait(api, plain["job_id"], {"done"})["film"] == "pixel centres"
    film = wait(api, asked["job_id"], {"done"})["film"]
    assert film.startswith("pixel centres: engine dacrt")
    assert images[0] == images[1]


def test_coverage_and_depth_layers_follow_the_primary_hits(api, box_scene, scene_id) -> None:
    """coverage is 1 exactly where AO sampled (a hit), depth is Cycles' Z pass: the
    closest hit's camera-space depth, 1e10 on background."""
    job = create(api, scene_id, 40, 30, spp=2, seed=5)
    assert wait(api, job["job_id"], {"done", "failed", "cancelled"})["state"] == "done"

    def layer(name: str) -> np.ndarray:
        raw = api.client.get(f"/v1/jobs/{job['job_id']}/result", params={"format": name})
        assert raw.status_code == 200, raw.text
        return np.frombuffer(raw.content, "<f4")

    coverage, depth = layer("coverage"), layer("depth")
    cam = Camera.from_dict(camera(40, 30))
    origins, directions, tmin, tmax = cam.rays()
    bvh = kernels.build_bvh(*box_scene, device="cpu")
    used = kernels.render_ao(bvh, origins, directions, spp=2, seed=5, tmin=tmin, tmax=tmax)
    np.testing.assert_array_equal(coverage, (used.spp_used > 0).astype(np.float32))
    assert 0 < coverage.mean() < 1  # the box fills part of the view
    assert np.all(depth[coverage == 0] == 1e10)
    # Each hit point's distance from the camera along its view axis.
    hits = kernels.trace(bvh, origins, directions, tmin, tmax)
    hit = coverage == 1
    points = origins[hit] + hits.t[hit, None] * directions[hit]
    np.testing.assert_allclose(depth[hit], (points - cam.position) @ cam.forward, rtol=1e-5)


def _layer(api, scene_id: str, name: str, cam: dict, **params) -> np.ndarray:
    """One result layer of a finished job on `cam`, as (height, width)."""
    response = api.client.post("/v1/jobs", json={"scene_id": scene_id, "camera": cam,
                                                 "spp": 1, **params})  # fmt: skip
    assert response.status_code == 202, response.text
    job = response.json()
    assert wait(api, job["job_id"], {"done", "failed", "cancelled"})["state"] == "done"
    raw = api.client.get(f"/v1/jobs/{job['job_id']}/result", params={"format": name})
    return np.frombuffer(raw.content, "<f4").reshape(job["height"], job["width"])


def test_a_window_is_that_part_of_the_whole_frame(api, scene_id) -> None:
    """A border render: the window's pixels are the frame's pixels there, exactly."""
    full = _layer(api, scene_id, "depth", camera(40, 30))
    window = {"x": 7, "y": 11, "width": 20, "height": 9}
    part = _layer(api, scene_id, "depth", camera(40, 30), window=window)
    assert part.shape == (9, 20)
    np.testing.assert_array_equal(part, full[11:20, 7:27])
    assert (part < 1e10).any() and (part == 1e10).any()  # box edge inside the window


@pytest.mark.parametrize(
    ("fit", "half_fine_pixel"), [("HORIZONTAL", 1 / 160), ("VERTICAL", 1 / 60)]
)
def test_pixel_aspect_two_to_one_is_every_other_column_of_a_finer_frame(
    api, scene_id, fit: str, half_fine_pixel: float
) -> None:
    """Pixels twice as wide as tall (aspect 2:1) lie on every other column of a square-
    pixel camera twice as wide, shifted half of its pixel (Blender's viewplane): with the
    width fitted a fine pixel is s/80, with the height fitted s/30 (s: the fitted side)."""
    coarse = {**camera(40, 30), "sensor_fit": fit}
    wide = _layer(api, scene_id, "depth", coarse, pixel_aspect=[2.0, 1.0])
    finer = {**camera(80, 30), "sensor_fit": fit}
    finer["shift_x"] += half_fine_pixel  # in units of s
    fine = _layer(api, scene_id, "depth", finer)
    assert wide.shape == (30, 40)
    np.testing.assert_allclose(wide, fine[:, ::2], rtol=1e-5)
    square = _layer(api, scene_id, "depth", coarse)
    assert not np.allclose(wide, square)  # the aspect changed what the pixels see


def test_a_window_outside_the_frame_is_refused(api, scene_id) -> None:
    body = {"scene_id": scene_id, "camera": camera(40, 30),
            "window": {"x": 30, "y": 0, "width": 20, "height": 10}}  # fmt: skip
    response = api.client.post("/v1/jobs", json=body)
    assert response.status_code == 422 and "does not fit" in response.text


def test_events_stream_progress_until_the_end(api, service, scene_id) -> None:
    job = create(api, scene_id, 64, 48, spp=16, seed=1)
    events: list[tuple[str, dict]] = []
    with httpx.stream(
        "GET", f"{service.url}/v1/jobs/{job['job_id']}/events", timeout=POLL_LIMIT_S,
        headers=service.auth,
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


def test_a_cancelled_job_stops_and_the_worker_goes_on(api, scene_id) -> None:
    """End to end with the real engine (test_gated_work.py holds the job where it wants
    it): a queued job cancelled never starts, a running one stops and has no result, and
    the worker goes on."""
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
    no_result = api.client.get(f"/v1/jobs/{big['job_id']}/result")
    assert no_result.status_code == 409 and no_result.json()["parameter"] == "job_id"
    small = create(api, scene_id, 16, 12, spp=1)
    assert wait(api, small["job_id"], {"done", "failed", "cancelled"})["state"] == "done"


def test_a_long_poll_answers_as_the_job_ends(api, scene_id) -> None:
    """?wait=S: a running job's status after S seconds; a short job's as soon as it ends,
    its whole time counted; a final job's at once; S over 10 is refused, naming wait."""
    big = create(api, scene_id, 512, 384, spp=4096)  # a minute's work, cancelled below
    start = time.perf_counter()
    held = api.client.get(f"/v1/jobs/{big['job_id']}", params={"wait": 0.3})
    assert held.status_code == 200 and held.json()["state"] in ("queued", "running")
    assert time.perf_counter() - start >= 0.3
    api.client.delete(f"/v1/jobs/{big['job_id']}")
    small = create(api, scene_id, 16, 12, spp=1)
    start = time.perf_counter()
    ended = api.client.get(f"/v1/jobs/{small['job_id']}", params={"wait": 10}, timeout=30)
    assert ended.json()["state"] == "done" and "total" in ended.json()["timings_ms"]
    assert time.perf_counter() - start < 9.0  # the end, not the 10 s, answered it
    start = time.perf_counter()
    again = api.client.get(f"/v1/jobs/{small['job_id']}", params={"wait": 10}, timeout=30)
    assert again.json() == ended.json() and time.perf_counter() - start < 9.0
    refused = api.client.get(f"/v1/jobs/{small['job_id']}", params={"wait": 11})
    assert refused.status_code == 422 and "wait" in refused.text


def test_denoise_reaches_the_engine_and_the_status_says_so(api, box_scene, scene_id) -> None:
    """denoise=true: the job's image is `render_ao(denoise=True)`'s, its status says
    denoised and its estimate is the raw render's."""
    origins, directions, tmin, tmax = Camera.from_dict(camera(40, 30)).rays()
    bvh = kernels.build_bvh(*box_scene, device="cpu")
    job = create(api, scene_id, 40, 30, spp=2, seed=4, denoise=True)
    status = wait(api, job["job_id"], {"done", "failed", "cancelled"})
    assert status["state"] == "done", status
    assert status["denoised"] is True
    raw = api.client.get(f"/v1/jobs/{job['job_id']}/result", params={"format": "f32"})
    got = np.frombuffer(raw.content, "<f4")
    expected = kernels.render_ao(bvh, origins, directions, spp=2, seed=4, tmin=tmin, tmax=tmax,
                                 denoise=True, image_shape=(30, 40))
    np.testing.assert_allclose(got, expected.ao, atol=1e-6)
    assert status["rmse_estimate"] == pytest.approx(expected.rmse_estimate)
    plain = wait(api, create(api, scene_id, 40, 30, spp=2, seed=4)["job_id"], {"done"})
    assert plain["denoised"] is False


def test_denoise_without_the_extra_is_a_422_naming_it(start_service, tmp_path) -> None:
    """A service whose Python cannot import pyoidn refuses denoise=true with a 422 that
    names the field and the extra to install, and still renders without it."""
    stub = tmp_path / "hide" / "pyoidn"
    stub.mkdir(parents=True)
    (stub / "__init__.py").write_text('raise ImportError("pyoidn hidden by the test")\n')
    hidden = Api(start_service(env={"PYTHONPATH": str(stub.parent)}))
    try:
        sid = hidden.upload(*floor_and_box()).json()["scene_id"]
        body = {"scene_id": sid, "camera": camera(20, 15), "spp": 2, "denoise": True}
        response = hidden.client.post("/v1/jobs", json=body)
        assert response.status_code == 422, response.text
        problem = response.json()
        assert problem["parameter"] == "denoise"
        assert 'pip install "scenesort[denoise]"' in problem["detail"] + problem["fix"]
        body["denoise"] = False
        assert hidden.client.post("/v1/jobs", json=body).status_code == 202
    finally:
        hidden.client.close()
