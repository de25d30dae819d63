"""The add-on registers and unregisters cleanly, twice, and never pulls in the engine."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import bpy
import pytest
from blender_scenes import REPO

import addon

OPERATORS = (
    "server_start", "server_restart", "server_stop", "server_status", "open_log", "build_bvh",
    "render_ao",
)  # fmt: skip
SETTINGS = ("method", "leaf_size", "spp", "target_error", "max_pixel_error", "ao_distance",
            "engine")


def _registered() -> bool:
    return hasattr(bpy.types.Scene, "scenesort")


def test_register_unregister_twice() -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    for _ in range(2):
        addon.register()
        assert _registered()
        scene = bpy.context.scene
        for name in SETTINGS:
            assert hasattr(scene.scenesort, name), name
        assert "server_url" not in scene.scenesort.bl_rna.properties  # a preference now
        prefs = bpy.context.preferences.addons["addon"].preferences
        assert (prefs.server_url, prefs.port, prefs.device) == ("", 0, "cpu")
        assert prefs.start_on_render and not prefs.allow_remote and not prefs.server_command
        assert scene.scenesort.method == "sah" and scene.scenesort.leaf_size == 8
        for name in OPERATORS:
            # `get_rna_type` fails for an operator that is not registered.
            assert getattr(bpy.ops.scenesort, name).get_rna_type().identifier
        assert hasattr(bpy.types, "SCENESORT_PT_render")
        assert hasattr(bpy.types, "SCENESORT_PT_view3d")
        assert hasattr(bpy.context.window_manager, "scenesort")
        addon.unregister()
        assert not _registered()
        assert not hasattr(bpy.types, "SCENESORT_PT_render")
        assert not hasattr(bpy.types.WindowManager, "scenesort")
        assert bpy.context.preferences.addons.get("addon") is None  # the entry it made


def test_settings_survive_with_defaults_documented(registered: bpy.types.Scene) -> None:
    """Enum items are the names the service accepts."""
    props = registered.scenesort
    rna = props.bl_rna.properties
    assert {i.identifier for i in rna["method"].enum_items} == {"sah", "median"}
    assert {i.identifier for i in rna["engine"].enum_items} == {"bvh", "dacrt"}
    assert rna["leaf_size"].hard_min == 1 and rna["leaf_size"].hard_max == 64
    assert rna["spp"].hard_max == 4096  # the service's limit


def test_addon_imports_neither_warp_nor_the_project() -> None:
    """Inside Blender only the standard library and numpy exist: check in a clean process."""
    code = (
        "import sys, bpy, addon; addon.register(); addon.unregister();"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in "
        "{'warp', 'scenesort', 'kernels', 'backend', 'fastapi', 'httpx', 'uvicorn', "
        "'requests'});"
        "print('BAD', bad); sys.exit(1 if bad else 0)"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]


def test_preferences_round_trip_through_blenders_userpref(tmp_path) -> None:
    """Saved with Blender's preferences (never a .blend) and read back by a new session."""
    env = {**os.environ, **{f"BLENDER_USER_{d.upper()}": str(tmp_path / d)
                            for d in ("config", "scripts", "datafiles", "extensions")}}  # fmt: skip
    values = [8777, False, True, "http://127.0.0.1:8777", "tok", r"C:\Tools\scenesort.exe",
              "cuda:0"]  # fmt: skip
    names = ["port", "start_on_render", "allow_remote", "server_url", "server_token",
             "server_command"]  # fmt: skip
    save = (
        "import bpy, addon; addon.register();"
        "p = bpy.context.preferences.addons['addon'].preferences;"
        f"{', '.join('p.' + n for n in names)}, p.device_name = {values!r};"
        "bpy.ops.wm.save_userpref()"
    )
    load = (
        "import json, bpy, addon; bpy.ops.wm.read_userpref(); addon.register();"
        "p = bpy.context.preferences.addons['addon'].preferences;"
        f"print(json.dumps([{', '.join('p.' + n for n in names)}, p.device]))"
    )
    for code in (save, load):
        proc = subprocess.run(
            [sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True,
            timeout=120,
        )  # fmt: skip
        assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert json.loads(proc.stdout.strip().splitlines()[-1]) == values


class _Layout:
    """Takes every UILayout call the panel makes (Blender only draws with a window)."""

    alert = enabled = False

    def __init__(self, calls: list) -> None:
        self.calls = calls

    def __getattr__(self, name: str):  # noqa: ANN204
        def call(*args: object, **kwargs: object) -> _Layout:
            self.calls.append((name, args, kwargs))
            return _Layout(self.calls)

        return call


@pytest.mark.parametrize("state", ["offline", "connected", "mismatch", "other_device"])
def test_panel_draws_in_every_state(registered, state: str, monkeypatch) -> None:
    from addon import panel, service

    status = bpy.context.window_manager.scenesort
    status.connected = state != "offline"
    status.mismatch = state == "mismatch"
    status.device = "cuda:0" if state == "other_device" else "cpu"
    calls: list = []
    ours = state in {"mismatch", "other_device"}
    monkeypatch.setattr(service, "running", lambda: ours)  # a child of ours runs
    panel.draw(_Layout(calls), bpy.context)
    operators = {args[0] for name, args, _ in calls if name == "operator"}
    assert ("scenesort.server_restart" in operators) == ours
    assert {"scenesort.build_bvh", "scenesort.render_ao"} <= operators
