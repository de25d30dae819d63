"""Frame ranges against a real service that the add-on starts: per frame only what changed
is sent (meshes after a HEAD by hash, the instance list when it changed), and Ctrl-F12
gives the images `scenesort render-frames` makes of the exported bundle."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import bpy
import numpy as np
import pytest
from blender_scenes import FRAMES, animated_scene, read_image
from scenesort.backend.commands import main

import addon
from addon import connection, export, pipeline, prefs, service
from addon.tasks import Task


@pytest.fixture(scope="module")
def live() -> Iterator[bpy.types.Scene]:
    """blender_scenes' animated scene and a service started by the add-on."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon.register()
    try:  # a failed start still unregisters: the next module registers again
        scene = animated_scene(bpy.context.scene)
        assert bpy.ops.scenesort.server_start() == {"FINISHED"}
        yield scene
    finally:
        proc = service._process
        addon.unregister()
        assert proc is None or proc.poll() is not None, "unregister left the service running"


def _send(scene: bpy.types.Scene, frame: int) -> list[str]:
    """Frame `frame`'s instance list made sure of on the service, as a frame of Ctrl-F12
    does; the requests it took."""
    scene.frame_set(frame)
    listing = export.export_instances(bpy.context.evaluated_depsgraph_get())
    target = prefs.target(bpy.context)

    def body(task: Task) -> list[str]:
        client = connection.connect(task, target).client
        start = len(client.requests)
        pipeline.ensure_instances(task, client, listing, pipeline.Outcome())
        return client.requests[start:]

    return Task(body).run()


def test_frames_send_only_what_changed(live) -> None:
    """Frame 1 sends its three meshes and its list; frame 2 only the deformed blob and the
    new list (the cube moved); frame 4 repeats frame 3's instances (only the camera moved)
    and sends nothing; every mesh is asked for by HEAD first."""
    sent = {frame: _send(live, frame) for frame in FRAMES}
    puts = {f: sum(r.startswith("PUT /v1/meshes/") for r in sent[f]) for f in FRAMES}
    heads = {f: sum(r.startswith("HEAD /v1/meshes/") for r in sent[f]) for f in FRAMES}
    lists = {f: sent[f].count("POST /v1/instance-scenes") for f in FRAMES}
    assert heads == {1: 3, 2: 3, 3: 3, 4: 3}
    assert puts == {1: 3, 2: 1, 3: 1, 4: 0}
    assert lists == {1: 1, 2: 1, 3: 1, 4: 0}
    assert all(r.startswith(("HEAD", "PUT", "POST", "GET /v1/health")) for f in FRAMES
               for r in sent[f])


def test_ctrl_f12_gives_render_frames_images(live, tmp_path: Path) -> None:
    """The engine's frame range (instance lists on the service) and `scenesort
    render-frames` on the exported bundle give the same AO and coverage, frame by frame."""
    scene = live
    settings = scene.render.image_settings
    scene.render.engine, scene.render.film_transparent = "SCENESORT", True
    settings.file_format, settings.color_depth = "OPEN_EXR", "32"
    scene.render.filepath = str(tmp_path / "engine" / "frame_")
    assert bpy.ops.render.render(animation=True) == {"FINISHED"}
    assert bpy.ops.scenesort.export_animation(directory=str(tmp_path / "bundle")) == {"FINISHED"}
    assert main(["render-frames", str(tmp_path / "bundle"), "--out", str(tmp_path / "cli"),
                 "--no-progress"]) == 0
    for frame in FRAMES:
        rgba = read_image(tmp_path / "engine" / f"frame_{frame:04d}.exr")
        ao = np.load(tmp_path / "cli" / f"{frame:06d}.npy")
        coverage = rgba[..., 3]  # the scene's pixel filter: partly covered at edges
        assert 0.2 < (coverage == 1.0).mean() < 1.0 and ((coverage > 0) & (coverage < 1)).any()
        # Cycles' AO pass: the hits' samples (the job's AO counts a miss as 1)
        np.testing.assert_array_equal(rgba[..., 0], np.maximum(ao + coverage - 1.0, 0.0))
        np.testing.assert_array_equal(ao[coverage == 0], 1.0)
