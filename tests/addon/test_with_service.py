"""Against a real service that the add-on's own `scenesort.server_start` launches.

Build fills the timings (and reuses a cached BVH), Render AO fills `scenesort AO`
with exactly what the service returns for the same rays sent directly, and a
second render of an unchanged scene uploads nothing.
"""

from __future__ import annotations

import math
import os
import shlex
import sys
from collections.abc import Iterator
from pathlib import Path

import bpy
import httpx
import numpy as np
import pytest
from conftest import REPO, add_camera, add_object, box_mesh, free_port

import addon
from addon import camera, export, image, pipeline, prefs, service
from addon.tasks import Task

WIDTH, HEIGHT = 40, 30


def _launcher() -> str:
    """The `scenesort` console script of this environment, else the module."""
    script = Path(sys.executable).with_name("scenesort")
    if script.exists():
        return shlex.quote(str(script))
    return shlex.join([sys.executable, "-m", "backend.cli"])


def _grid_mesh(name: str, n: int, size: float) -> bpy.types.Mesh:
    """An n x n grid of quads in the z=0 plane: a floor with 2*n*n triangles."""
    xs = np.linspace(-size / 2, size / 2, n + 1)
    verts = [(x, y, 0.0) for y in xs for x in xs]
    faces = [
        (j * (n + 1) + i, j * (n + 1) + i + 1, (j + 1) * (n + 1) + i + 1, (j + 1) * (n + 1) + i)
        for j in range(n)
        for i in range(n)
    ]
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(verts, [], faces)
    return mesh


def _uploads() -> int:
    """Scene uploads the service logged so far (one line per request)."""
    log = service.log_path()
    return log.read_text(errors="replace").count("POST /v1/scenes?") if log else 0


@pytest.fixture(scope="module")
def live() -> Iterator[bpy.types.Scene]:
    """A floor with a box on it, a camera, and a service started by the add-on."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon.register()
    old_env = {k: os.environ.get(k) for k in (prefs.COMMAND_ENV, "PYTHONPATH")}
    os.environ[prefs.COMMAND_ENV] = _launcher()
    os.environ["PYTHONPATH"] = str(REPO)  # for the `-m backend.cli` fallback
    scene = bpy.context.scene
    add_object(scene, "Floor", _grid_mesh("Floor", 8, 8.0))
    add_object(scene, "Box", box_mesh("Box", size=1.5), (0.0, 0.0, 0.75))
    add_camera(scene, (0.0, -7.0, 4.0), (math.radians(60), 0.0, 0.0), WIDTH, HEIGHT)
    scene.scenesort.server_url = f"http://127.0.0.1:{free_port()}"
    scene.scenesort.ao_distance = 2.0
    try:
        yield scene
    finally:
        proc = service._process
        addon.unregister()  # must stop the service it started
        assert proc is None or proc.poll() is not None, "unregister left the service running"
        for key, value in old_env.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def test_start_launches_the_service(live) -> None:
    assert bpy.ops.scenesort.server_start() == {"FINISHED"}
    status = bpy.context.window_manager.scenesort
    assert status.connected and status.version and status.device == "cpu"
    assert service.running()
    pid = service._process.pid
    # A second start finds it running and launches nothing.
    assert bpy.ops.scenesort.server_start() == {"FINISHED"}
    assert "already running" in status.message
    assert service._process.pid == pid


def test_build_fills_timings_and_reuses_the_bvh(live) -> None:
    props = live.scenesort
    triangles = export.export_scene(bpy.context.evaluated_depsgraph_get()).triangles
    assert triangles == 2 * 8 * 8 + 12
    assert bpy.ops.scenesort.build_bvh() == {"FINISHED"}
    assert props.has_build and not props.build_cached
    assert props.build_triangles == triangles
    assert props.build_total_ms > 0 and props.build_mtris_per_s > 0
    assert props.build_nodes >= 1 and props.build_sah_cost > 0
    assert len(props.build_phases) >= 1 and all(p.ms >= 0 for p in props.build_phases)
    assert [(r.method, r.leaf_size) for r in props.build_history] == [("sah", 8)]
    uploads = _uploads()

    assert bpy.ops.scenesort.build_bvh() == {"FINISHED"}  # unchanged: cached, no upload
    assert props.build_cached and len(props.build_history) == 1
    assert _uploads() == uploads
    assert bpy.context.window_manager.scenesort.last_upload_bytes == 0

    props.method, props.leaf_size = "median", 16
    try:
        assert bpy.ops.scenesort.build_bvh() == {"FINISHED"}
        assert not props.build_cached
        assert [(r.method, r.leaf_size) for r in props.build_history] == [
            ("median", 16),
            ("sah", 8),
        ]
    finally:
        props.method, props.leaf_size = "sah", 8


def _direct_ao(scene: bpy.types.Scene, scene_id: str) -> np.ndarray:
    """The service's answer for the engine camera model's rays, sent without the add-on."""
    from kernels import Camera

    desc = camera.camera_dict(scene, bpy.context.evaluated_depsgraph_get())
    origins, directions, _, _ = Camera.from_dict(desc).rays()
    props = scene.scenesort
    body = np.concatenate([origins, directions], axis=1).astype("<f4").tobytes()
    params = {"rays": len(origins), "spp": props.spp, "seed": props.seed,
              "distance": props.ao_distance, "method": props.method,
              "leaf_size": props.leaf_size}  # fmt: skip
    resp = httpx.post(
        f"{props.server_url}/v1/scenes/{scene_id}/ao", params=params, content=body,
        headers={"Content-Type": "application/octet-stream"}, timeout=600.0,
    )  # fmt: skip
    assert resp.status_code == 200, resp.text
    return np.frombuffer(resp.content, dtype="<f4")


def _image_ao() -> np.ndarray:
    img = bpy.data.images[image.IMAGE_NAME]
    pixels = np.empty(len(img.pixels), dtype=np.float32)
    img.pixels.foreach_get(pixels)
    rgba = pixels.reshape(img.size[1], img.size[0], 4)
    return rgba[::-1, :, 0].ravel()  # bottom row first in Blender; top row first here


def test_render_matches_the_services_direct_result(live) -> None:
    live.scenesort.spp, live.scenesort.seed = 8, 3
    assert bpy.ops.scenesort.render_ao() == {"FINISHED"}
    img = bpy.data.images[image.IMAGE_NAME]
    assert tuple(img.size) == (WIDTH, HEIGHT)
    ours = _image_ao()
    mesh = export.export_scene(bpy.context.evaluated_depsgraph_get())
    from addon.client import scene_id

    direct = _direct_ao(live, scene_id(len(mesh.vertices), mesh.triangles, mesh.body()))
    np.testing.assert_array_equal(ours, direct)
    assert ours.min() >= 0.0 and ours.max() <= 1.0
    assert (ours > 0).mean() > 0.3  # the floor fills most of the view
    assert ours.std() > 0.05  # shading varies: not a constant image


def test_second_render_uploads_nothing(live) -> None:
    uploads = _uploads()
    assert uploads >= 1
    first = _image_ao()
    assert bpy.ops.scenesort.render_ao() == {"FINISHED"}
    assert _uploads() == uploads
    assert bpy.context.window_manager.scenesort.last_upload_bytes == 0
    assert live.scenesort.build_cached  # the BVH was reused, not rebuilt
    np.testing.assert_array_equal(_image_ao(), first)  # same seed, same scene


def test_changed_scene_is_uploaded_again(live) -> None:
    uploads = _uploads()
    bpy.data.objects["Box"].location.x += 1.0
    try:
        assert bpy.ops.scenesort.render_ao() == {"FINISHED"}
        assert _uploads() == uploads + 1
        assert bpy.context.window_manager.scenesort.last_upload_bytes > 0
    finally:
        bpy.data.objects["Box"].location.x -= 1.0


def test_interactive_job_path_gives_the_same_image(live) -> None:
    """invoke() renders through the jobs API (progress, cancel); same pixels as execute()."""
    assert bpy.ops.scenesort.render_ao() == {"FINISHED"}
    scripted = _image_ao()
    depsgraph = bpy.context.evaluated_depsgraph_get()
    settings = pipeline.Settings.from_scene(live.scenesort)
    mesh = export.export_scene(depsgraph)
    desc = camera.camera_dict(live, depsgraph)
    task = Task(lambda t: pipeline.render_job(t, settings, mesh, desc))
    outcome = task.run()
    assert outcome.uploaded_bytes == 0  # the scene was already there
    assert any("%" in step for step in task.steps), task.steps  # progress was reported
    np.testing.assert_array_equal(outcome.ao, scripted)


def test_stop_ends_the_service(live) -> None:
    proc = service._process
    assert bpy.ops.scenesort.server_stop() == {"FINISHED"}
    assert proc.poll() is not None and not service.running()
    with pytest.raises(RuntimeError, match="No scenesort service is running"):
        bpy.ops.scenesort.build_bvh()
