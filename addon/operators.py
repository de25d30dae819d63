"""Operators: start/stop the service, refresh its status, build the BVH, render AO.

`execute()` runs to completion (scripts, headless tests); `invoke()` runs the HTTP
work on a thread, polled by a modal timer that shows progress in the status bar and
the panel, and Esc cancels. `cancel()` (Blender ends a modal run: a file load, a
closed window) and a `load_pre` handler stop the work and clear the busy state.
Failures are reported in words for the user, stored in `window_manager.scenesort`
for the panel, and leave the scene untouched.
"""

from __future__ import annotations

import time
import traceback
from typing import Any

import bpy
from bpy.app.handlers import persistent

from . import camera, export, image, pipeline, prefs, service, timings
from .client import ServiceError
from .connection import Connection, VersionMismatch, connect
from .tasks import Cancelled, Task

_EXPECTED = (ServiceError, service.LaunchError, ValueError, Cancelled)

_active: Task | None = None  # one request (start, build, render) at a time


def _status(context: bpy.types.Context) -> Any:
    return context.window_manager.scenesort


def _redraw(context: bpy.types.Context) -> None:
    for window in context.window_manager.windows:
        for area in window.screen.areas:
            if area.type in {"PROPERTIES", "VIEW_3D", "PREFERENCES"}:
                area.tag_redraw()


def _release(status: Any | None) -> None:
    """No request runs any more: the buttons work again."""
    global _active
    _active = None
    if status is not None:
        status.busy, status.progress = False, ""


def _fail(op: bpy.types.Operator, context: bpy.types.Context, exc: BaseException) -> set[str]:
    """Report an error in the user's words, keep it for the panel, and cancel."""
    if isinstance(exc, _EXPECTED):
        message = str(exc) or "Cancelled"
    else:  # a bug: still no exception escapes, but the console gets the traceback
        traceback.print_exception(exc)
        message = f"Unexpected error ({type(exc).__name__}: {exc}); see the system console"
    status = _status(context)
    status.error = message
    status.mismatch = isinstance(exc, VersionMismatch)
    status.busy, status.progress = False, ""
    op.report({"ERROR"}, message)
    _redraw(context)
    return {"CANCELLED"}


def _remember(context: bpy.types.Context, connection: Connection) -> None:
    """What the service's health answer says, for the panel and the Device menu."""
    status = _status(context)
    health = connection.health
    status.connected, status.mismatch, status.error = True, False, ""
    status.url = connection.client.base_url
    status.version = str(health.get("version", "?"))
    status.device = str(health.get("device", "?"))
    prefs.remember_devices(health)


class _TaskOperator:
    """Shared run logic: prepare on the main thread, work in a Task, apply on the main thread."""

    _task: Task | None = None
    _timer = None
    _started_at = 0.0

    def prepare(self, context: bpy.types.Context) -> Task:
        raise NotImplementedError

    def apply(self, context: bpy.types.Context, outcome: Any) -> str:
        raise NotImplementedError

    def _begin(self, context: bpy.types.Context) -> Task:
        global _active
        if _active is not None:
            raise ServiceError("scenesort is still working on the previous request")
        task = self.prepare(context)
        _active = task
        status = _status(context)
        status.busy, status.error, status.progress = True, "", task.step
        return task

    def _finish(self, context: bpy.types.Context, task: Task) -> set[str]:
        _release(_status(context))
        if task.error is not None:
            return _fail(self, context, task.error)
        try:
            message = self.apply(context, task.result)
        except Exception as exc:  # noqa: BLE001
            return _fail(self, context, exc)
        _status(context).message = message
        self.report({"INFO"}, message)
        _redraw(context)
        return {"FINISHED"}

    def execute(self, context: bpy.types.Context) -> set[str]:
        try:
            task = self._begin(context)
        except Exception as exc:  # noqa: BLE001
            return _fail(self, context, exc)
        try:
            task.run()
        except Exception as exc:  # noqa: BLE001 - handed to _finish, which reports it
            task.error = exc
        return self._finish(context, task)

    def invoke(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        try:
            self._task = self._begin(context)
        except Exception as exc:  # noqa: BLE001
            return _fail(self, context, exc)
        self._task.start()
        self._started_at = time.monotonic()
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.1, window=context.window)
        wm.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        task = self._task
        if event.type == "ESC" and event.value == "PRESS":
            self.cancel(context)  # the thread stops at its next step; its answer is dropped
            _status(context).message = "Cancelled"
            self.report({"WARNING"}, "scenesort: cancelled")
            return {"CANCELLED"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        if not task.done:
            elapsed = time.monotonic() - self._started_at
            _status(context).progress = f"{task.step} ({elapsed:.0f} s)"
            if context.workspace is not None:
                context.workspace.status_text_set(
                    f"scenesort: {task.step}... {elapsed:.0f} s (Esc to cancel)"
                )
            _redraw(context)
            return {"RUNNING_MODAL"}
        self._stop_ui(context)
        return self._finish(context, task)

    def cancel(self, context: bpy.types.Context) -> None:
        """Blender ends the modal run (Esc, a file load, a closed window): stop the work
        at its next step and clear the busy state."""
        if self._task is not None:
            self._task.cancel()
        self._stop_ui(context)
        _release(_status(context))
        _redraw(context)

    def _stop_ui(self, context: bpy.types.Context) -> None:
        if self._timer is not None:
            context.window_manager.event_timer_remove(self._timer)
            self._timer = None
        if context.workspace is not None:
            context.workspace.status_text_set(None)


class SCENESORT_OT_server_status(_TaskOperator, bpy.types.Operator):
    """Ask the service for its version and device"""

    bl_idname = "scenesort.server_status"
    bl_label = "Check Service"

    def prepare(self, context: bpy.types.Context) -> Task:
        target = prefs.target(context, start=False)
        return Task(lambda task: connect(task, target))

    def apply(self, context: bpy.types.Context, outcome: Connection) -> str:
        _remember(context, outcome)
        status = _status(context)
        return f"scenesort {status.version} on {status.device} at {status.url}"


class _StartOperator(_TaskOperator):
    """Start the local service (unless one answers) and wait for its health answer."""

    def prepare(self, context: bpy.types.Context) -> Task:
        target = prefs.target(context, start=True)
        if target.url:
            service.host_port(target.url)  # a remote URL: say that it cannot be started
        return Task(lambda task: connect(task, target))

    def apply(self, context: bpy.types.Context, outcome: Connection) -> str:
        _remember(context, outcome)
        where = "started" if outcome.started else "already running"
        return f"Service {where} at {outcome.client.base_url}"


class SCENESORT_OT_server_start(_StartOperator, bpy.types.Operator):
    """Start the local scenesort service with Blender's own Python (unless one answers)"""

    bl_idname = "scenesort.server_start"
    bl_label = "Start Local Service"


class SCENESORT_OT_server_restart(_StartOperator, bpy.types.Operator):
    """Stop the local service that Blender started and start it again (e.g. after the
    add-on was updated, or to use another device)"""

    bl_idname = "scenesort.server_restart"
    bl_label = "Restart Local Service"

    def prepare(self, context: bpy.types.Context) -> Task:
        service.stop()
        _status(context).connected = False
        return super().prepare(context)


class SCENESORT_OT_server_stop(bpy.types.Operator):
    """Stop the scenesort service that Blender started"""

    bl_idname = "scenesort.server_stop"
    bl_label = "Stop Service"

    def execute(self, context: bpy.types.Context) -> set[str]:
        status = _status(context)
        if service.stop():
            status.connected, status.mismatch = False, False
            status.message = "Service stopped"
            self.report({"INFO"}, status.message)
            _redraw(context)
            return {"FINISHED"}
        self.report({"WARNING"}, "No service started by Blender is running")
        return {"CANCELLED"}


class SCENESORT_OT_open_log(bpy.types.Operator):
    """Open the log of the local service (its output and errors) in the system's viewer"""

    bl_idname = "scenesort.open_log"
    bl_label = "Open Service Log"

    def execute(self, context: bpy.types.Context) -> set[str]:
        path = service.log_path()
        if path is None or not path.exists():
            self.report({"WARNING"}, "No service log yet: the local service has not started")
            return {"CANCELLED"}
        bpy.ops.wm.path_open(filepath=str(path))
        return {"FINISHED"}


def _apply_build(context: bpy.types.Context, outcome: pipeline.Outcome, settings: Any) -> str:
    props = context.scene.scenesort
    timings.apply_build(props, outcome.build, settings.method, settings.leaf_size)
    _status(context).last_upload_bytes = outcome.uploaded_bytes
    cached = " (cached)" if props.build_cached else ""
    return (
        f"BVH {props.build_method}/{props.build_leaf_size}: {props.build_triangles:,} "
        f"triangles in {props.build_total_ms:.1f} ms{cached}"
    )


class SCENESORT_OT_build_bvh(_TaskOperator, bpy.types.Operator):
    """Send the scene to the service (if it changed) and build its BVH; shows the timings"""

    bl_idname = "scenesort.build_bvh"
    bl_label = "Build BVH"

    def prepare(self, context: bpy.types.Context) -> Task:
        target = prefs.target(context)
        settings = pipeline.Settings.from_scene(context.scene)
        mesh = export.export_scene(context.evaluated_depsgraph_get())
        self._settings = settings
        return Task(lambda task: pipeline.build(task, target, settings, mesh))

    def apply(self, context: bpy.types.Context, outcome: pipeline.Outcome) -> str:
        _remember(context, outcome.connection)
        return _apply_build(context, outcome, self._settings)


class SCENESORT_OT_render_ao(_TaskOperator, bpy.types.Operator):
    """Render ambient occlusion from the scene camera into the image 'scenesort AO'"""

    bl_idname = "scenesort.render_ao"
    bl_label = "Render AO"

    def prepare(self, context: bpy.types.Context) -> Task:
        scene = context.scene
        target = prefs.target(context)
        settings = pipeline.Settings.from_scene(scene)
        depsgraph = context.evaluated_depsgraph_get()
        view = camera.view(scene, depsgraph)
        mesh = export.export_scene(depsgraph)
        self._settings = settings
        # The engine's one path, for scripts (execute) and the UI (invoke) alike.
        return Task(lambda task: pipeline.render_job(task, target, settings, mesh, view))

    def apply(self, context: bpy.types.Context, outcome: pipeline.Outcome) -> str:
        _remember(context, outcome.connection)
        width, height = outcome.size
        build = ""
        if outcome.build is not None:
            build = "; " + _apply_build(context, outcome, self._settings)
        status = _status(context)
        pipeline.remember(status, outcome)
        img = image.write_ao_image(outcome)
        image.show_in_image_editors(context.window_manager, img)
        return f"AO {width}x{height} in {outcome.render_ms / 1e3:.1f} s{build}"


@persistent
def _on_load_pre(*_args: Any) -> None:
    """A file is about to load: drop the running request, so nothing stays busy after."""
    if _active is not None:
        _active.cancel()
    wm = bpy.context.window_manager
    _release(None if wm is None else wm.scenesort)


CLASSES = (
    SCENESORT_OT_server_status,
    SCENESORT_OT_server_start,
    SCENESORT_OT_server_restart,
    SCENESORT_OT_server_stop,
    SCENESORT_OT_open_log,
    SCENESORT_OT_build_bvh,
    SCENESORT_OT_render_ao,
)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.app.handlers.load_pre.append(_on_load_pre)


def unregister() -> None:
    if _on_load_pre in bpy.app.handlers.load_pre:
        bpy.app.handlers.load_pre.remove(_on_load_pre)
    if _active is not None:
        _active.cancel()
    _release(None)
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
