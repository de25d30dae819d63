"""With no service: every operator reports a clear error, cancels, and changes nothing."""

from __future__ import annotations

import math
import shlex
import sys

import bpy
import pytest
from blender_scenes import add_camera, add_object, box_mesh, free_port

from addon import image, prefs, service
from addon.connection import check_remote

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


def _prefs() -> prefs.SCENESORT_AP_preferences:
    return prefs.preferences(bpy.context)


@pytest.fixture
def offline_scene(registered: bpy.types.Scene) -> bpy.types.Scene:
    """A box and a camera; the service URL names a port where nothing listens."""
    add_object(registered, "Box", box_mesh("Box"))
    add_camera(registered, (0.0, -6.0, 2.0), (math.radians(75), 0.0, 0.0), 16, 12)
    _prefs().server_url = f"http://127.0.0.1:{free_port()}"
    _prefs().start_on_render = False
    return registered


@pytest.mark.parametrize("name", OPERATORS)
def test_no_service_reports_clear_error_and_changes_nothing(offline_scene, name) -> None:
    before = _snapshot(offline_scene)
    url = _prefs().server_url
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
    _prefs().server_url = f"http://127.0.0.1:{free_port()}"
    with pytest.raises(RuntimeError, match="no visible, renderable mesh"):
        bpy.ops.scenesort.build_bvh()


def test_bad_url_is_explained(offline_scene) -> None:
    _prefs().server_url = "localhost:8765"  # no scheme
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


def test_a_remote_url_is_refused_unless_allowed(offline_scene) -> None:
    """A URL off this computer would receive the scene: only with both switches on."""
    url = "http://192.0.2.1:8765"  # TEST-NET-1: never routed
    _prefs().server_url = url
    before = _snapshot(offline_scene)
    for name in ("build_bvh", "render_ao", "server_status", "server_start"):
        with pytest.raises(RuntimeError, match="'Allow a remote service'"):
            getattr(bpy.ops.scenesort, name)()
    _prefs().allow_remote = True
    assert not bpy.app.online_access  # bpy's default: Blender's own switch still refuses
    with pytest.raises(RuntimeError, match="online access is off"):
        bpy.ops.scenesort.build_bvh()
    assert _snapshot(offline_scene) == before and not service.running()
    assert check_remote(url, allow_remote=True, online_access=True) == url
    for local in ("http://127.0.0.1:1", "http://localhost:1", "http://[::1]:1"):
        assert check_remote(local, allow_remote=False, online_access=False) == local


def test_no_local_service_and_no_start_says_how(offline_scene) -> None:
    """Port 0 and 'Start the service on first render' off: nothing to talk to, no launch."""
    _prefs().server_url = ""
    with pytest.raises(RuntimeError, match="press 'Start Local Service', or turn on"):
        bpy.ops.scenesort.render_ao()
    assert not service.running()
