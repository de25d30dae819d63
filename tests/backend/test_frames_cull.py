"""Culling in frames: a camera moving across a field of instances larger than its
view renders the same images with culling on and off (bit for bit, with the request's AO
distance and with the scene default), never builds a mesh that stays out of view, builds
one when it enters the view, and reuses the top level while the same instances are in view;
the service's jobs the same."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from bundles import look_at_camera
from scenesort.backend.render.bundle import BundleWriter, mesh_id
from scenesort.backend.render.frames import FrameRenderer, FrameResult
from test_render_frames import at, box, grid, service_frame, upload_meshes


def scaled(mesh: tuple[np.ndarray, np.ndarray], s: float) -> tuple[np.ndarray, np.ndarray]:
    v, f = mesh
    return (v * np.float32([s, s, 1.5 * s])).astype(np.float32), f


FLOOR = grid(8, 36.0)
WEST, MIDDLE, EAST = (scaled(box(), s) for s in (0.6, 0.5, 0.7))  # three distinct meshes


def field() -> list:
    """Boxes 1 apart on x in [-16, 16], three rows: x < -1 west's, x > 8 east's, between them
    middle's; and the floor under them all."""
    out = [(FLOOR, at(0.0, 0.0))]
    for x in range(-16, 17):
        mesh = WEST if x < -1 else EAST if x > 8 else MIDDLE
        out += [(mesh, at(float(x), float(y))) for y in (-1, 0, 1)]
    return out


# The camera (about 0.6 wide at the floor) moves east: the same instances in view from 1 to
# 2, middle's entering on the way (by 3 with the default AO distance, 3.6; by 4 with 0.5);
# east's stay out of reach. (The reach is the distance plus the lift bound, 3.1 here.)
CAMERAS = {1: (-11.5, 0.5), 2: (-11.49, 0.51), 3: (-8.5, 0.5), 4: (-3.5, 0.5), 5: (-1.5, -0.5)}


def write(root: Path, distance: float | None) -> Path:
    writer = BundleWriter()
    writer.settings = {**writer.settings, "distance": distance}
    for number, (x, y) in CAMERAS.items():
        writer.frame(number, look_at_camera((x, y, 1.6)), field())
    return writer.write(root)


@pytest.fixture(scope="module", params=[0.5, None], ids=["distance", "default"])
def bundle(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write(tmp_path_factory.mktemp("field"), request.param)


@pytest.fixture(scope="module")
def both(bundle: Path) -> dict[bool, dict[int, FrameResult]]:
    """The frames rendered with culling (True) and without (False), interleaved."""
    renderers = {cull: FrameRenderer(bundle, cull=cull) for cull in (True, False)}
    out: dict[bool, dict[int, FrameResult]] = {True: {}, False: {}}
    for number in CAMERAS:
        for cull, renderer in renderers.items():
            out[cull][number] = renderer.render(number)
    return out


def test_images_are_those_without_culling(both) -> None:
    for number in CAMERAS:
        culled, full = both[True][number], both[False][number]
        np.testing.assert_array_equal(culled.ao, full.ao)
        np.testing.assert_array_equal(culled.depth, full.depth)
        np.testing.assert_array_equal(culled.coverage, full.coverage)
        assert full.coverage.all() and (full.ao < 1).any()  # the floor, some occlusion
    assert not np.array_equal(both[True][1].ao, both[True][5].ao)  # middle's in view


def test_what_is_out_of_view_is_not_built(both) -> None:
    """Many instances are culled in every frame; east's mesh is never built; middle's is
    skipped until it enters the view, built then, reused after; a camera move that keeps
    the same instances in view (frame 2) builds nothing. Without culling, frame 1 builds
    every mesh."""
    floor, west, middle, east = (mesh_id(*m) for m in (FLOOR, WEST, MIDDLE, EAST))
    reports = {n: r.build for n, r in both[True].items()}
    instances = len(field())
    for number, report in reports.items():
        assert 0.4 * instances < report.culled < instances, number
        assert east in report.skipped
        assert east not in report.built + report.refit + report.reused
    assert sorted(reports[1].built) == sorted([floor, west])
    assert sorted(reports[1].skipped) == sorted([middle, east])
    assert reports[2].cached and reports[2].top_level == "reused"
    enters = next(n for n, r in reports.items() if middle not in r.skipped)
    assert 2 < enters < max(CAMERAS) and reports[enters].built == [middle]  # frames after
    assert all(middle in r.reused and not r.built for n, r in reports.items() if n > enters)
    full = {n: r.build for n, r in both[False].items()}
    assert all(r.culled == 0 and not r.skipped for r in full.values())
    assert sorted(full[1].built) == sorted([floor, west, middle, east])
    assert all(reports[n].bvh_bytes < full[n].bvh_bytes for n in CAMERAS)


def test_service_jobs_cull_and_render_the_same(api, tmp_path) -> None:  # noqa: ANN001
    """The service's jobs (culling by default) answer the frames' images without culling,
    and their build reports say what was culled and skipped."""
    bundle = write(tmp_path, None)
    reference = FrameRenderer(bundle, cull=False)
    upload_meshes(api, bundle)
    east = mesh_id(*EAST)
    for number in (1, 4):
        status, job_id = service_frame(api, bundle, number)
        assert status["build"]["culled"] > 0 and east in status["build"]["skipped"]
        answer = api.client.get(f"/v1/jobs/{job_id}/result", params={"format": "f32"})
        service_ao = np.frombuffer(answer.content, "<f4").reshape(18, 24)
        np.testing.assert_array_equal(service_ao, reference.render(number).ao)
