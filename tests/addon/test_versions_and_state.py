"""Version check, the Device menu, and no busy state left by a cancel or a file load.

The "services" here are small standard-library HTTP servers that answer
`GET /v1/health` like scenesort does (another version, or CUDA devices this machine
does not have: the GPU is the one thing mocked); one of them runs as the add-on's own
child process, started through the "Service command" override.
"""

from __future__ import annotations

import json
import shlex
import sys
import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import bpy
import pytest
from blender_scenes import add_camera, add_object, box_mesh

from addon import operators, prefs, service
from addon.connection import ADDON_VERSION
from addon.tasks import Task

# A stand-in service: prints the line `scenesort serve` prints, then answers health.
FAKE_SERVICE = """
import http.server, json, sys
class Health(http.server.BaseHTTPRequestHandler):
    def do_GET(self):
        body = json.dumps({"version": sys.argv[1], "device": "cpu", "devices": ["cpu"]})
        self.send_response(200)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body.encode())
    def log_message(self, *args):
        pass
server = http.server.HTTPServer(("127.0.0.1", 0), Health)
print(f"scenesort serving on http://127.0.0.1:{server.server_address[1]}", flush=True)
server.serve_forever()
"""


def _prefs() -> prefs.SCENESORT_AP_preferences:
    return prefs.preferences(bpy.context)


def _health_server(answer: dict, seen: list | None = None) -> Iterator[str]:
    """A health endpoint; `seen` collects the Authorization header of each request."""
    body = json.dumps(answer).encode()

    class Handler(BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 - http.server's naming
            if seen is not None:
                seen.append(self.headers.get("Authorization"))
            self.send_response(200)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args: object) -> None:
            pass

    httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}"
    finally:
        httpd.shutdown()
        httpd.server_close()


@pytest.fixture
def old_service() -> Iterator[str]:
    yield from _health_server({"version": "0.0.1", "device": "cpu", "devices": ["cpu"]})


@pytest.fixture
def gpu_service() -> Iterator[str]:
    answer = {"version": ADDON_VERSION, "device": "cpu", "devices": ["cpu", "cuda:0", "cuda:1"]}
    yield from _health_server(answer)


def test_a_service_of_another_version_is_reported(registered, old_service) -> None:
    add_object(registered, "Box", box_mesh("Box"))
    add_camera(registered, (0.0, -6.0, 2.0), (1.3, 0.0, 0.0), 8, 6)
    _prefs().server_url = old_service
    message = f"is scenesort 0.0.1 but the add-on is {ADDON_VERSION}"
    for name in ("server_status", "build_bvh", "render_ao"):
        with pytest.raises(RuntimeError, match=message):
            getattr(bpy.ops.scenesort, name)()
        status = bpy.context.window_manager.scenesort
        assert status.mismatch and message in status.error and not status.busy
    assert not registered.scenesort.has_build  # nothing was sent or built


def test_a_mismatch_of_our_own_service_offers_a_restart(registered, tmp_path, monkeypatch) -> None:
    script = tmp_path / "old_scenesort.py"
    script.write_text(FAKE_SERVICE)
    monkeypatch.setenv(prefs.COMMAND_ENV, shlex.join([sys.executable, str(script), "0.0.1"]))
    with pytest.raises(RuntimeError, match="press 'Restart Local Service'"):
        bpy.ops.scenesort.server_start()
    assert service.running() and bpy.context.window_manager.scenesort.mismatch
    first = service._process.pid
    with pytest.raises(RuntimeError, match="press 'Restart Local Service'"):
        bpy.ops.scenesort.server_restart()  # still the old program: still refused
    assert service.running() and service._process.pid != first  # but it did restart it
    monkeypatch.setenv(prefs.COMMAND_ENV, shlex.join([sys.executable, str(script), ADDON_VERSION]))
    assert bpy.ops.scenesort.server_restart() == {"FINISHED"}
    status = bpy.context.window_manager.scenesort
    assert status.connected and not status.mismatch and status.version == ADDON_VERSION
    assert status.url == service.served_url()


def test_device_menu_lists_the_devices_the_service_reports(registered, gpu_service) -> None:
    p = _prefs()
    prefs._reported.clear()  # what an earlier test's service reported
    assert p.device == "cpu" and [i[0] for i in prefs._device_items(p, bpy.context)] == ["cpu"]
    p.server_url = gpu_service
    assert bpy.ops.scenesort.server_status() == {"FINISHED"}
    names = [item[0] for item in prefs._device_items(p, bpy.context)]
    assert names == ["cpu", "cuda:0", "cuda:1"]
    p.device = "cuda:1"
    assert p.device_name == "cuda:1" and prefs.target(bpy.context).device == "cuda:1"
    p.server_url = ""
    argv = service.command_line("", "127.0.0.1", 0, prefs.target(bpy.context).device)
    assert argv[-2:] == ["--device", "cuda:1"]


def test_a_service_of_your_own_gets_its_token(registered) -> None:
    seen: list = []
    server = _health_server({"version": ADDON_VERSION, "device": "cpu"}, seen)
    url = next(server)
    try:
        p = _prefs()
        p.server_url, p.server_token = url, "own-secret"
        assert bpy.ops.scenesort.server_status() == {"FINISHED"}
        p.server_token = ""
        assert bpy.ops.scenesort.server_status() == {"FINISHED"}
    finally:
        server.close()
    assert seen == ["Bearer own-secret", None]
    assert prefs.target(bpy.context).token == ""
    p.server_url, p.server_token = "", "own-secret"
    assert prefs.target(bpy.context).token == ""  # never sent to the local service


class _Probe(operators._TaskOperator):
    """The operators' shared run logic, outside Blender's operator machinery."""

    def report(self, kind: set[str], message: str) -> None:
        pass


def _blocked_task() -> tuple[Task, threading.Event]:
    release = threading.Event()

    def body(task: Task) -> None:
        task.set_step("waiting for the service")
        release.wait(30)
        task.set_step("after the wait")

    task = Task(body)
    task.start()
    return task, release


def test_cancel_clears_busy_and_stops_the_work(registered) -> None:
    """What Blender calls when a modal run ends early (closed window, file load)."""
    probe = _Probe()
    probe._task, release = _blocked_task()
    operators._active = probe._task
    status = bpy.context.window_manager.scenesort
    status.busy, status.progress = True, "waiting for the service"
    probe.cancel(bpy.context)
    release.set()
    probe._task._thread.join(30)
    assert probe._task.cancelled and probe._task.steps == ["waiting for the service"]
    assert operators._active is None and not status.busy and status.progress == ""


def test_file_load_leaves_nothing_busy(registered, tmp_path: Path) -> None:
    task, release = _blocked_task()
    operators._active = task
    bpy.context.window_manager.scenesort.busy = True
    path = tmp_path / "other.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.open_mainfile(filepath=str(path))
    release.set()
    task._thread.join(30)
    assert task.cancelled and operators._active is None
    assert not bpy.context.window_manager.scenesort.busy
    _prefs().server_url = "http://127.0.0.1:1"  # nothing listens: the request itself runs
    with pytest.raises(RuntimeError, match="No scenesort service is running"):
        bpy.ops.scenesort.server_status()
