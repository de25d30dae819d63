"""`scenesort render-frames` and backend/render/: the skip rules by the build reports,
the frames against the flattened scene and against the service's jobs for the same frames,
resume, and bad bundles named by file and field."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from bundles import look_at_camera
from scenesort.backend.commands import main
from scenesort.backend.render import frames as frames_module
from scenesort.backend.render.bundle import (
    BundleError,
    BundleWriter,
    instance_body,
    mesh_body,
    mesh_id,
    read_bundle,
)
from scenesort.backend.render.frames import FrameRenderer, render_frames
from service_client import OCTET, job_ended


def grid(n: int, size: float, lift: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """An n x n grid of quads in the z=0 plane, bent up by `lift` * x^2 (a deformation)."""
    xs = np.linspace(-size / 2, size / 2, n + 1, dtype=np.float32)
    gx, gy = np.meshgrid(xs, xs, indexing="xy")
    v = np.stack([gx.ravel(), gy.ravel(), lift * gx.ravel() ** 2], axis=1).astype(np.float32)
    quads = [(j * (n + 1) + i, j * (n + 1) + i + 1, (j + 1) * (n + 1) + i + 1,
              (j + 1) * (n + 1) + i) for j in range(n) for i in range(n)]
    f = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    return v, np.array(f, np.int32)


def box() -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (0.0, 1.0)],
                 np.float32)
    f = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
         [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    return v, np.array(f, np.int32)


def at(x: float, y: float, z: float = 0.0, sx: float = 1.0) -> np.ndarray:
    m = np.zeros((3, 4), np.float32)
    m[:, :3] = np.diag([sx, 1.0, 1.0])
    m[:, 3] = (x, y, z)
    return m


FLOOR, CUBE = grid(6, 8.0), box()
BLOB0, BLOB1 = grid(4, 1.5, 0.0), grid(4, 1.5, 0.4)
CAM1, CAM2 = look_at_camera((0.0, 0.0, 6.0)), look_at_camera((0.5, 0.2, 5.5))


def scene_of(frame: int) -> list:
    """Frame 2 moves only the camera, 3 moves a cube (mirrored), 4 deforms the blob, and 5
    is frame 1 again (after the blob's BVH was refit into frame 4's shape)."""
    second_cube = at(1.5, 0.0) if frame < 3 or frame == 5 else at(1.5, 1.0, sx=-1.0)
    blob = BLOB1 if frame == 4 else BLOB0
    return [(FLOOR, at(0, 0)), (CUBE, at(-1.5, 0.0)), (CUBE, second_cube),
            (blob, at(0.0, -1.5, 0.5))]


FRAME_CAMERAS = {1: CAM1, 2: CAM2, 3: CAM2, 4: CAM2, 5: CAM1}


@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory) -> Path:
    writer = BundleWriter(settings={"spp": 4, "seed": 1, "distance": 1.0})
    for number, camera in FRAME_CAMERAS.items():
        writer.frame(number, camera, scene_of(number))
    return writer.write(tmp_path_factory.mktemp("bundle"))


@pytest.fixture(scope="module")
def rendered(bundle: Path) -> dict[int, frames_module.FrameResult]:
    renderer = FrameRenderer(bundle)
    return {n: renderer.render(n) for n in FRAME_CAMERAS}


def test_only_what_changed_is_built(rendered) -> None:
    """Frame 1 builds its three meshes and the top level; 2 (camera only) builds nothing;
    3 (a transform) only the top level; 4 (the blob deformed) refits the blob alone; 5
    (frame 1's list again) refits the blob back: its earlier BVH now held frame 4's. Every
    instance is within the cameras' reach here, so culling changes none of this (it has
    its own tests: test_frames_cull.py)."""
    floor, cube, blob0, blob1 = (mesh_id(*m) for m in (FLOOR, CUBE, BLOB0, BLOB1))
    reports = {n: r.build for n, r in rendered.items()}
    assert all(r.culled == 0 and not r.skipped for r in reports.values())
    assert sorted(reports[1].built) == sorted([floor, cube, blob0])
    assert reports[1].top_level == "built" and not reports[1].refit
    assert reports[2].top_level == "reused" and reports[2].cached
    assert not reports[2].built and not reports[2].refit and "top_level" not in \
        reports[2].timings_ms
    assert reports[3].top_level == "built" and not reports[3].built and not reports[3].refit
    assert sorted(reports[3].reused) == sorted([floor, cube, blob0])
    assert reports[4].refit == [blob1] and not reports[4].built
    assert reports[4].top_level == "built" and sorted(reports[4].reused) == sorted([floor, cube])
    assert reports[5].refit == [blob0] and reports[5].top_level == "built"


def test_a_frame_again_is_the_same_image(rendered) -> None:
    """Frame 5 is frame 1's scene and camera: the refits between them leave no trace."""
    np.testing.assert_array_equal(rendered[5].ao, rendered[1].ao)
    np.testing.assert_array_equal(rendered[5].depth, rendered[1].depth)
    assert not np.array_equal(rendered[2].ao, rendered[1].ao)  # the camera moved


def _flattened(frame: int) -> tuple[np.ndarray, np.ndarray]:
    vertices, indices, start = [], [], 0
    for (v, i), m in scene_of(frame):
        world = v.astype(np.float64) @ m[:, :3].T.astype(np.float64) + m[:, 3]
        vertices.append(world.astype(np.float32))
        indices.append((i[:, ::-1] if np.linalg.det(m[:, :3]) < 0 else i) + start)
        start += len(v)
    return np.concatenate(vertices), np.concatenate(indices)


def test_frames_match_the_flattened_scene(bundle, rendered) -> None:
    """Each frame's coverage, depth and AO are those of its flattened triangles traced with
    one BVH (the same camera rays and samples; a path through the engine without the
    instance levels, bit for bit for the AO)."""
    from scenesort.backend.render import camera_render

    from scenesort import kernels

    for number, result in rendered.items():
        bvh = kernels.build_bvh(*_flattened(number))
        camera = camera_render.job_camera(read_bundle(bundle).frame(number).request)
        o, d, tmin, tmax = camera.rays()
        hits = kernels.trace(bvh, o, d, tmin, tmax)
        np.testing.assert_array_equal(result.coverage.ravel() > 0, hits.hit)
        z = hits.t.astype(np.float64) * (d.astype(np.float64) @ camera.forward)
        flat_depth = np.where(hits.hit, z, camera_render.BACKGROUND_DEPTH).astype(np.float32)
        np.testing.assert_allclose(result.depth.ravel(), flat_depth, rtol=1e-5)  # t in float32
        flat = kernels.render_ao(bvh, o, d, spp=4, seed=1, distance=1.0, tmin=tmin, tmax=tmax)
        np.testing.assert_array_equal(result.ao.ravel(), flat.ao)  # the same samples


def test_cli_writes_the_service_jobs_images(bundle, api, tmp_path) -> None:  # noqa: ANN001
    """render-frames' .npy per frame equals the AO of the service's job for that frame
    (meshes PUT by hash, the frame's instance list, the frame's camera and settings); the
    jobs' build reports follow the same rules."""
    assert main(["render-frames", str(bundle), "--out", str(tmp_path), "--no-progress"]) == 0
    upload_meshes(api, bundle)
    for number in FRAME_CAMERAS:
        status, job_id = service_frame(api, bundle, number)
        if number == 2:
            assert status["build"]["top_level"] == "reused" and not status["build"]["built"]
        result = api.client.get(f"/v1/jobs/{job_id}/result", params={"format": "f32"})
        service_ao = np.frombuffer(result.content, "<f4").reshape(18, 24)
        np.testing.assert_array_equal(np.load(tmp_path / f"{number:06d}.npy"), service_ao)
        png = api.client.get(f"/v1/jobs/{job_id}/result", params={"format": "png"})
        assert (tmp_path / f"{number:06d}.png").read_bytes() == png.content


def upload_meshes(api, bundle: Path) -> None:  # noqa: ANN001
    """PUT the bundle's meshes to the service by their hashes."""
    meta = json.loads((bundle / "manifest.json").read_text())
    for name, info in meta["meshes"].items():
        body = (bundle / "meshes" / f"{name}.bin").read_bytes()
        answer = api.client.put(f"/v1/meshes/{name}", content=body, headers=OCTET, params={
            "vertices": info["vertices"], "triangles": info["triangles"]})
        assert answer.status_code in (200, 201), answer.text


def service_frame(api, bundle: Path, number: int) -> tuple[dict, str]:  # noqa: ANN001
    """The frame rendered as a service job (its instance list, camera and the bundle's
    settings; meshes uploaded first): the finished job's status and id."""
    meta = json.loads((bundle / "manifest.json").read_text())
    record = json.loads((bundle / "frames" / f"{number:06d}.json").read_text())
    body = (bundle / "frames" / f"{number:06d}.bin").read_bytes()
    listing = api.client.post("/v1/instance-scenes", content=body, headers=OCTET, params={
        "meshes": record["meshes"], "instances": record["instances"]})
    assert listing.status_code in (200, 201), listing.text
    job = api.client.post("/v1/jobs", json={
        "scene_id": listing.json()["scene_id"], "camera": record["camera"],
        **meta["settings"]}).json()
    status = job_ended(api.client, job["job_id"])
    assert status["state"] == "done", status
    return status, job["job_id"]


def test_resume_and_frame_ranges(bundle, tmp_path) -> None:
    done = render_frames(bundle, tmp_path, frames=[2, 3], progress=False)
    assert [n for n, _ in done] == [2, 3] and all(r is not None for _, r in done)
    again = render_frames(bundle, tmp_path, frames=[1, 2, 3], resume=True, progress=False)
    assert [(n, r is None) for n, r in again] == [(1, False), (2, True), (3, True)]
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        f"{n:06d}.{ext}" for n in (1, 2, 3) for ext in ("npy", "png")]


def test_cli_frames_option_and_its_errors(bundle, tmp_path, capsys) -> None:
    assert main(["render-frames", str(bundle), "--out", str(tmp_path), "--frames", "4-5",
                 "--no-progress"]) == 0
    assert sorted(p.stem for p in tmp_path.glob("*.png")) == ["000004", "000005"]
    assert "2 frames rendered" in capsys.readouterr().out
    assert main(["render-frames", str(bundle), "--out", str(tmp_path), "--frames", "5-4"]) == 2
    assert "--frames" in capsys.readouterr().out
    assert main(["render-frames", str(bundle), "--out", str(tmp_path), "--frames", "9"]) == 2
    assert "frame 9 is not in the bundle" in capsys.readouterr().out


def _broken(bundle: Path, tmp_path: Path, change) -> Path:  # noqa: ANN001
    import shutil

    root = tmp_path / "broken"
    shutil.copytree(bundle, root)
    change(root)
    return root


def _edit_manifest(root: Path, **fields) -> None:
    path = root / "manifest.json"
    path.write_text(json.dumps({**json.loads(path.read_text()), **fields}))


@pytest.mark.parametrize(("change", "words"), [
    (lambda r: (r / "manifest.json").unlink(), "manifest.json: cannot be read"),
    (lambda r: _edit_manifest(r, version=2), "format version 2"),
    (lambda r: _edit_manifest(r, settings={"spp": 4, "samples": 9}), "samples"),
    (lambda r: _edit_manifest(r, settings={"spp": 0}), "spp"),
    (lambda r: (r / "meshes" / f"{mesh_id(*CUBE)}.bin").write_bytes(
        mesh_body(CUBE[0] + 1, CUBE[1])), "hashes to"),
    (lambda r: (r / "frames" / "000001.bin").write_bytes(
        instance_body(["0" * 32], [1], np.zeros((1, 3, 4)))), "000001.bin: body"),
])
def test_bad_bundles_are_refused_naming_the_file(bundle, tmp_path, capsys, change,
                                                 words) -> None:
    root = _broken(bundle, tmp_path, change)
    assert main(["render-frames", str(root), "--out", str(tmp_path / "out"), "--frames", "1",
                 "--no-progress"]) == 2
    out = capsys.readouterr().out.replace("\n", "")
    assert words in out, out
    with pytest.raises(BundleError):
        FrameRenderer(root).render(1)
