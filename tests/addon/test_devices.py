"""The local service's device: probed once by a child (cached), the first CUDA device by
default, another choice stops the running service, macOS CPU only with the reason."""

from __future__ import annotations

import json
import shlex
import sys
from collections.abc import Iterator

import bpy
import pytest

import addon
from addon import devices, prefs, service
from tests.waiting import until

FAKE_GPUS = "print('[\"cpu\", \"cuda:0\", \"cuda:1\"]')"  # what a two-GPU machine prints
SLEEPER = shlex.join([sys.executable, "-c", "import time; time.sleep(60)"])


@pytest.fixture
def fresh(monkeypatch: pytest.MonkeyPatch, tmp_path) -> Iterator[None]:
    """No answer in this session or on disk (a config folder of the test's own)."""
    monkeypatch.setenv("BLENDER_USER_CONFIG", str(tmp_path / "config"))
    devices.forget()
    yield
    devices.forget()


def _prefs() -> prefs.SCENESORT_AP_preferences:
    return prefs.preferences(bpy.context)


def _no_child(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
    raise AssertionError("the probe ran again")


def test_the_probe_asks_warp_in_a_child_once_and_caches_it(registered, fresh, monkeypatch):
    import warp

    warp.init()
    expected = [d.alias for d in warp.get_devices()]  # Warp's answer in this process
    assert devices.found() == expected
    cached = json.loads(devices.cache_path().read_text())
    assert cached["devices"] == expected and cached["key"][0] == sys.executable
    devices.forget()  # a new session: the file answers
    monkeypatch.setattr(devices.subprocess, "run", _no_child)
    assert devices.found() == expected


def test_the_first_cuda_device_is_the_default(registered, fresh, monkeypatch) -> None:
    monkeypatch.setattr(devices, "PROBE", FAKE_GPUS)
    p = _prefs()
    assert p.device_name == ""  # nothing chosen
    assert prefs.target(bpy.context).device == "cuda:0"  # the probe ran here
    assert [i[0] for i in prefs._device_items(p, bpy.context)] == ["cpu", "cuda:0", "cuda:1"]
    assert p.device == "cuda:0"
    p.device = "cpu"
    assert p.device_name == "cpu" and prefs.target(bpy.context).device == "cpu"
    argv = service.command_line("", "127.0.0.1", 0, prefs.target(bpy.context).device)
    assert argv[-2:] == ["--device", "cpu"]


def test_choosing_another_device_stops_the_running_service(registered, fresh, monkeypatch):
    monkeypatch.setattr(devices, "PROBE", FAKE_GPUS)
    p = _prefs()
    assert prefs.target(bpy.context).device == "cuda:0"
    proc = service.start(SLEEPER, "http://127.0.0.1:1")
    try:
        p.device = "cuda:0"  # the device it has: it keeps running
        assert service.running() and service._process is proc
        p.device = "cuda:1"
        assert not service.running() and proc.poll() is not None  # the next render starts it
    finally:
        service.stop()


def test_a_failed_probe_means_the_cpu_and_is_tried_again_later(registered, fresh, monkeypatch):
    monkeypatch.setattr(devices, "PROBE", "raise SystemExit(3)")
    assert devices.found() == ["cpu"] and devices.default() == "cpu"
    assert not devices.cache_path().exists()


def test_macos_probes_nothing_and_says_why(registered, fresh, monkeypatch) -> None:
    monkeypatch.setattr(devices.subprocess, "run", _no_child)
    monkeypatch.setattr(sys, "platform", "darwin")
    assert devices.found() == ["cpu"]
    items = prefs._device_items(_prefs(), bpy.context)
    assert [(i[0], i[2]) for i in items] == [("cpu", devices.MACOS_REASON)]


def test_blenders_ui_probes_at_enable_and_headless_blender_when_needed(fresh, monkeypatch):
    """Enabling the add-on in Blender's UI finds the GPUs on a thread (the Device menu
    lists them before any render or service start); a headless Blender probes nothing
    until a render needs the device."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    with monkeypatch.context() as patch:
        patch.setattr(devices.subprocess, "run", _no_child)
        addon.register()  # headless (bpy.app.background): nothing probed
        addon.unregister()
    assert devices.known() == ["cpu"] and devices._found is None
    monkeypatch.setattr(devices, "PROBE", FAKE_GPUS)
    monkeypatch.setattr(addon, "interactive", lambda: True)
    addon.register()
    try:
        until(lambda: devices.known() == ["cpu", "cuda:0", "cuda:1"], "the probe at enable")
        assert json.loads(devices.cache_path().read_text())["devices"] == devices.known()
        assert not service.running()
    finally:
        addon.unregister()
