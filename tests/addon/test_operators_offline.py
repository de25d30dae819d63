"""With no service: every operator reports a clear error, cancels, and changes nothing."""

from __future__ import annotations

import math
import shlex
import sys

import bpy
import pytest
from conftest import add_camera, add_object, box_mesh, free_port

from addon import image, prefs, service

OPERATORS = ("build_bvh", "render_ao", "server_status")


def _snapshot(scene: bpy.types.Scene) -> dict:
    """Everything an operator could have touched in the user's data."""
    props = scene.scenesort
    values = {
        p.identifier: getattr(props, p.identifier)
        for p in props.bl_rna.properties
        if p.type not in {"COLLECTION", "POINTER"}
    }
    values["phases"] = len(props.build_phases)
    values["history"] = len(props.build_history)
    return {
        "settings": values,
        "objects": sorted(o.name for o in bpy.data.objects),
        "meshes": sorted(m.name for m in bpy.data.meshes),
        "images": sorted(i.name for i in bpy.data.images),
        "locations": [tuple(o.location) for o in bpy.data.objects],
        "resolution": (scene.render.resolution_x, scene.render.resolution_y),
    }


@pytest.fixture
def offline_scene(registered: bpy.types.Scene) -> bpy.types.Scene:
    add_object(registered, "Box", box_mesh("Box"))
    add_camera(registered, (0.0, -6.0, 2.0), (math.radians(75), 0.0, 0.0), 16, 12)
    registered.scenesort.server_url = f"http://127.0.0.1:{free_port()}"
    return registered


@pytest.mark.parametrize("name", OPERATORS)
def test_no_service_reports_clear_error_and_changes_nothing(offline_scene, name) -> None:
    before = _snapshot(offline_scene)
    url = offline_scene.scenesort.server_url
    # Blender turns an operator's ERROR report into RuntimeError for Python callers;
    # the operator itself returned CANCELLED without raising.
    with pytest.raises(RuntimeError, match=f"No scenesort service is running at {url}"):
        getattr(bpy.ops.scenesort, name)()
    status = bpy.context.window_manager.scenesort
    assert status.error.startswith("No scenesort service is running")
    assert not status.busy
    assert _snapshot(offline_scene) == before
    assert image.IMAGE_NAME not in bpy.data.images


def test_operators_work_again_after_a_failure(offline_scene) -> None:
    """A failed request leaves no stale 'busy' state behind."""
    for _ in range(2):
        with pytest.raises(RuntimeError, match="No scenesort service"):
            bpy.ops.scenesort.render_ao()


def test_render_without_camera_says_so(registered) -> None:
    add_object(registered, "Box", box_mesh("Box"))
    before = _snapshot(registered)
    with pytest.raises(RuntimeError, match="no active camera"):
        bpy.ops.scenesort.render_ao()
    assert _snapshot(registered) == before


def test_empty_scene_says_what_is_missing(registered) -> None:
    add_camera(registered, (0.0, -6.0, 2.0), (math.radians(75), 0.0, 0.0))
    hidden = add_object(registered, "Hidden", box_mesh("Hidden"))
    hidden.hide_render = True
    registered.scenesort.server_url = f"http://127.0.0.1:{free_port()}"
    with pytest.raises(RuntimeError, match="no visible, renderable mesh"):
        bpy.ops.scenesort.build_bvh()


def test_bad_url_is_explained(offline_scene) -> None:
    offline_scene.scenesort.server_url = "localhost:8765"  # no scheme
    with pytest.raises(RuntimeError, match="is not a service URL"):
        bpy.ops.scenesort.build_bvh()


def test_stop_without_service_cancels_quietly(registered) -> None:
    assert bpy.ops.scenesort.server_stop() == {"CANCELLED"}


def test_start_with_missing_program_explains(offline_scene, monkeypatch) -> None:
    monkeypatch.setenv(prefs.COMMAND_ENV, "/nonexistent/bin/scenesort")
    before = _snapshot(offline_scene)
    with pytest.raises(RuntimeError, match="was not found"):
        bpy.ops.scenesort.server_start()
    assert not service.running()
    assert _snapshot(offline_scene) == before


def test_start_with_program_that_exits_reports_its_exit(offline_scene, monkeypatch) -> None:
    code = "import sys; print('port already in use'); sys.exit(3)"
    monkeypatch.setenv(prefs.COMMAND_ENV, shlex.join([sys.executable, "-c", code]))
    with pytest.raises(RuntimeError, match=r"did not start: the service exited \(code 3\)"):
        bpy.ops.scenesort.server_start()
    assert "port already in use" in bpy.context.window_manager.scenesort.error
    assert not service.running()


def test_start_refuses_a_remote_url(offline_scene) -> None:
    offline_scene.scenesort.server_url = "http://192.0.2.1:8765"  # TEST-NET: never routed
    with pytest.raises(RuntimeError, match="Only a local service can be started"):
        bpy.ops.scenesort.server_start()
