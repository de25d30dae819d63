"""Against a real service that the add-on's own `scenesort.server_start` launches.

The launch is the add-on's default one: this interpreter (Blender's Python) runs the
engine found on its path (here the checkout, in Blender the extension's wheels), on
a free port; no SCENESORT_COMMAND, no preference set.

Build fills the timings (and reuses a cached BVH), Render AO fills `scenesort AO`
with exactly what the service returns for the same rays sent directly, and a
second render of an unchanged scene uploads nothing.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Iterator

import bpy
import numpy as np
import pytest
from blender_scenes import add_camera, add_object, ao_pass, box_mesh, direct_film, grid_mesh

import addon
from addon import camera, connection, export, image, pipeline, prefs, service
from addon.tasks import Task

WIDTH, HEIGHT = 40, 30


def _uploads() -> int:
    """Scene uploads the service logged so far (one line per request)."""
    log = service.log_path()
    return log.read_text(errors="replace").count("POST /v1/scenes?") if log else 0


@pytest.fixture(scope="module")
def live() -> Iterator[bpy.types.Scene]:
    """A floor with a box on it, a camera, and a service started by the add-on."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon.register()
    assert not prefs.server_command(prefs.preferences(bpy.context))
    scene = bpy.context.scene
    add_object(scene, "Floor", grid_mesh("Floor", 8, 8.0))
    add_object(scene, "Box", box_mesh("Box", size=1.5), (0.0, 0.0, 0.75))
    add_camera(scene, (0.0, -7.0, 4.0), (math.radians(60), 0.0, 0.0), WIDTH, HEIGHT)
    scene.scenesort.ao_distance = 2.0
    try:
        yield scene
    finally:
        proc = service._process
        addon.unregister()  # must stop the service it started
        assert proc is None or proc.poll() is not None, "unregister left the service running"


def test_start_launches_the_service(live) -> None:
    assert bpy.ops.scenesort.server_start() == {"FINISHED"}
    status = bpy.context.window_manager.scenesort
    assert status.connected and status.version and status.device == "cpu"
    assert service.running() and status.url == service.served_url()
    assert status.url.startswith("http://127.0.0.1:") and not status.url.endswith(":0")
    assert service._process.args[:3] == [sys.executable, "-s", "-m"]  # Blender's Python
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


def _image_rgba() -> np.ndarray:
    """`scenesort AO`'s pixels, (W*H, 4), the top row first."""
    img = bpy.data.images[image.IMAGE_NAME]
    pixels = np.empty(len(img.pixels), dtype=np.float32)
    img.pixels.foreach_get(pixels)
    rgba = pixels.reshape(img.size[1], img.size[0], 4)
    return rgba[::-1].reshape(-1, 4)  # bottom row first in Blender; top row first here


def _image_ao() -> np.ndarray:
    return _image_rgba()[:, 0]


def test_render_matches_the_engines_direct_result(live) -> None:
    live.scenesort.spp, live.scenesort.seed = 8, 3
    assert bpy.ops.scenesort.render_ao() == {"FINISHED"}
    img = bpy.data.images[image.IMAGE_NAME]
    assert tuple(img.size) == (WIDTH, HEIGHT)
    assert img.colorspace_settings.name == "Non-Color"
    rgba = _image_rgba()
    ours, coverage = rgba[:, 0], rgba[:, 3]
    depsgraph = bpy.context.evaluated_depsgraph_get()
    direct, alpha = direct_film(live, export.export_scene(depsgraph),
                                camera.camera_dict(live, depsgraph))
    # Through the scene's pixel filter (Cycles' default): alpha is the filtered coverage.
    np.testing.assert_array_equal(coverage, alpha.ravel())
    assert ((coverage > 0) & (coverage < 1)).any()
    # The direct answer counts a miss as 1.0; the image holds the hits' samples only.
    np.testing.assert_array_equal(ours, ao_pass(direct, alpha).ravel())
    assert np.all(direct[alpha == 0] == 1.0)
    np.testing.assert_array_equal(rgba[:, 1], ours)
    hit = coverage > 0
    assert 0.3 < hit.mean() < 1.0  # the floor fills most of the view, sky above it
    assert ours[hit].std() > 0.05  # shading varies: not a constant image


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
    """The render job the operator's invoke() runs on a thread gives execute()'s pixels."""
    assert bpy.ops.scenesort.render_ao() == {"FINISHED"}
    scripted = _image_ao()
    depsgraph = bpy.context.evaluated_depsgraph_get()
    settings = pipeline.Settings.from_scene(live)
    target = prefs.target(bpy.context)
    mesh = export.export_scene(depsgraph)
    view = camera.view(live, depsgraph)
    task = Task(lambda t: pipeline.render_job(t, target, settings, mesh, view))
    outcome = task.run()
    assert outcome.uploaded_bytes == 0  # the scene was already there
    assert any("%" in step for step in task.steps), task.steps  # progress was reported
    np.testing.assert_array_equal(ao_pass(outcome.ao, outcome.coverage), scripted)


def test_stop_ends_the_service(live) -> None:
    proc = service._process
    assert bpy.ops.scenesort.server_stop() == {"FINISHED"}
    assert proc.poll() is not None and not service.running()
    prefs.preferences(bpy.context).start_on_render = False
    with pytest.raises(RuntimeError, match="No scenesort service is running"):
        bpy.ops.scenesort.build_bvh()


@pytest.mark.slow
def test_first_render_starts_the_service_with_progress(live) -> None:
    """'Start the service on first render' (the default): Render AO alone is enough, and
    the start reports its progress as steps (the panel's progress line)."""
    prefs.preferences(bpy.context).start_on_render = True
    assert not service.running()
    task = Task(lambda t: connection.connect(t, prefs.target(bpy.context)))
    outcome = task.run()
    assert outcome.started and service.running()
    assert any(step.startswith("starting the service, ") for step in task.steps), task.steps
    assert bpy.ops.scenesort.server_stop() == {"FINISHED"}
    assert bpy.ops.scenesort.render_ao() == {"FINISHED"}  # starts it again by itself
    assert service.running() and bpy.context.window_manager.scenesort.url == service.served_url()
