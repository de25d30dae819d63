"""Operators: start/stop the service, refresh its status, build the BVH, render AO.

`execute()` runs to completion (scripts, headless tests); `invoke()` runs the HTTP
work on a thread, polled by a modal timer that shows progress in the status bar,
and Esc cancels. Failures are reported in words for the user, stored in
`window_manager.scenesort.error` for the panel, and leave the scene untouched.
"""

from __future__ import annotations

import time
import traceback
from typing import Any

import bpy

from . import camera, export, image, pipeline, prefs, service, timings
from .client import Client, ServiceError
from .tasks import Cancelled, Task

START_TIMEOUT_S = 90.0  # first start imports Warp and may compile kernels
POLL_S = 0.25
_EXPECTED = (ServiceError, service.LaunchError, ValueError, Cancelled)

_active: Task | None = None  # one build or render at a time


def _status(context: bpy.types.Context) -> Any:
    return context.window_manager.scenesort


def _redraw(context: bpy.types.Context) -> None:
    for window in context.window_manager.windows:
        for area in window.screen.areas:
            if area.type in {"PROPERTIES", "VIEW_3D"}:
                area.tag_redraw()


def _fail(op: bpy.types.Operator, context: bpy.types.Context, exc: BaseException) -> set[str]:
    """Report an error in the user's words, keep it for the panel, and cancel."""
    if isinstance(exc, _EXPECTED):
        message = str(exc) or "Cancelled"
    else:  # a bug: still no exception escapes, but the console gets the traceback
        traceback.print_exception(exc)
        message = f"Unexpected error ({type(exc).__name__}: {exc}); see the system console"
    status = _status(context)
    status.error = message
    status.busy = False
    status.progress = ""
    op.report({"ERROR"}, message)
    _redraw(context)
    return {"CANCELLED"}


def _remember_health(context: bpy.types.Context, health: dict) -> None:
    status = _status(context)
    status.connected = True
    status.version = str(health.get("version", "?"))
    status.device = str(health.get("device", "?"))
    status.error = ""


class SCENESORT_OT_server_status(bpy.types.Operator):
    """Ask the service for its version and device"""

    bl_idname = "scenesort.server_status"
    bl_label = "Check Service"

    def execute(self, context: bpy.types.Context) -> set[str]:
        status = _status(context)
        try:
            health = Client(context.scene.scenesort.server_url).health()
        except ServiceError as exc:
            status.connected = False
            return _fail(self, context, exc)
        _remember_health(context, health)
        self.report({"INFO"}, f"scenesort {status.version} on {status.device}")
        return {"FINISHED"}


class SCENESORT_OT_server_start(bpy.types.Operator):
    """Start the local scenesort service (scenesort serve) as a child of Blender"""

    bl_idname = "scenesort.server_start"
    bl_label = "Start Local Service"

    _deadline = 0.0
    _timer = None

    def _launch(self, context: bpy.types.Context) -> dict | None:
        """Health of a service already there, or None after launching ours."""
        url = context.scene.scenesort.server_url
        client = Client(url)
        try:
            return client.health()
        except ServiceError:
            pass
        service.start(prefs.server_command(context), url)
        self._deadline = time.monotonic() + START_TIMEOUT_S
        return None

    def _poll(self, context: bpy.types.Context) -> dict | None:
        """Health once the service answers; raises if it died or took too long."""
        try:
            return Client(context.scene.scenesort.server_url).health()
        except ServiceError:
            if not service.running():
                raise service.LaunchError(
                    f"The service did not start: {service.exit_message()}"
                ) from None
            if time.monotonic() > self._deadline:
                service.stop()
                raise service.LaunchError(
                    f"The service did not answer within {START_TIMEOUT_S:g} s; "
                    f"its log is {service.log_path()}"
                ) from None
            return None

    def _started(self, context: bpy.types.Context, health: dict, launched: bool) -> set[str]:
        _remember_health(context, health)
        status = _status(context)
        where = "started" if launched else "already running"
        status.message = f"Service {where} at {context.scene.scenesort.server_url}"
        self.report({"INFO"}, status.message)
        _redraw(context)
        return {"FINISHED"}

    def execute(self, context: bpy.types.Context) -> set[str]:
        try:
            health = self._launch(context)
            if health is not None:
                return self._started(context, health, launched=False)
            while (health := self._poll(context)) is None:
                time.sleep(POLL_S)
        except Exception as exc:  # noqa: BLE001 - reported to the user, never raised
            return _fail(self, context, exc)
        return self._started(context, health, launched=True)

    def invoke(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        try:
            health = self._launch(context)
        except Exception as exc:  # noqa: BLE001
            return _fail(self, context, exc)
        if health is not None:
            return self._started(context, health, launched=False)
        _status(context).progress = "Starting the service..."
        self._timer = context.window_manager.event_timer_add(POLL_S, window=context.window)
        context.window_manager.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        try:
            health = self._poll(context)
        except Exception as exc:  # noqa: BLE001
            self._end(context)
            return _fail(self, context, exc)
        if health is None:
            return {"RUNNING_MODAL"}
        self._end(context)
        return self._started(context, health, launched=True)

    def _end(self, context: bpy.types.Context) -> None:
        context.window_manager.event_timer_remove(self._timer)
        _status(context).progress = ""


class SCENESORT_OT_server_stop(bpy.types.Operator):
    """Stop the scenesort service that Blender started"""

    bl_idname = "scenesort.server_stop"
    bl_label = "Stop Service"

    def execute(self, context: bpy.types.Context) -> set[str]:
        status = _status(context)
        if service.stop():
            status.connected = False
            status.message = "Service stopped"
            self.report({"INFO"}, status.message)
            _redraw(context)
            return {"FINISHED"}
        self.report({"WARNING"}, "No service started by Blender is running")
        return {"CANCELLED"}


class _TaskOperator:
    """Shared run logic: prepare on the main thread, work in a Task, apply on the main thread."""

    _task: Task | None = None
    _timer = None
    _started_at = 0.0
    _interactive = False  # invoke(): work on a thread, shown in the status bar

    def prepare(self, context: bpy.types.Context) -> Task:
        raise NotImplementedError

    def apply(self, context: bpy.types.Context, outcome: pipeline.Outcome) -> str:
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
        global _active
        _active = None
        status = _status(context)
        status.busy, status.progress = False, ""
        if task.error is not None:
            return _fail(self, context, task.error)
        try:
            message = self.apply(context, task.result)
        except Exception as exc:  # noqa: BLE001
            return _fail(self, context, exc)
        status.message, status.connected = message, True
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
        self._interactive = True
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
        global _active
        task = self._task
        if event.type == "ESC" and event.value == "PRESS":
            task.cancel()  # the thread stops at its next step; its answer is dropped
            self._stop_ui(context)
            _active = None
            status = _status(context)
            status.busy, status.progress, status.message = False, "", "Cancelled"
            self.report({"WARNING"}, "scenesort: cancelled")
            return {"CANCELLED"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        if not task.done:
            elapsed = time.monotonic() - self._started_at
            text = f"scenesort: {task.step}... {elapsed:.0f} s (Esc to cancel)"
            _status(context).progress = task.step
            if context.workspace is not None:
                context.workspace.status_text_set(text)
            _redraw(context)
            return {"RUNNING_MODAL"}
        self._stop_ui(context)
        return self._finish(context, task)

    def _stop_ui(self, context: bpy.types.Context) -> None:
        context.window_manager.event_timer_remove(self._timer)
        if context.workspace is not None:
            context.workspace.status_text_set(None)


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
        settings = pipeline.Settings.from_scene(context.scene.scenesort)
        mesh = export.export_scene(context.evaluated_depsgraph_get())
        self._settings = settings
        return Task(lambda task: pipeline.build(task, settings, mesh))

    def apply(self, context: bpy.types.Context, outcome: pipeline.Outcome) -> str:
        return _apply_build(context, outcome, self._settings)


class SCENESORT_OT_render_ao(_TaskOperator, bpy.types.Operator):
    """Render ambient occlusion from the scene camera into the image 'scenesort AO'"""

    bl_idname = "scenesort.render_ao"
    bl_label = "Render AO"

    def prepare(self, context: bpy.types.Context) -> Task:
        scene = context.scene
        settings = pipeline.Settings.from_scene(scene.scenesort)
        depsgraph = context.evaluated_depsgraph_get()
        cam = camera.camera_dict(scene, depsgraph)
        mesh = export.export_scene(depsgraph)
        self._settings, self._size = settings, (cam["width"], cam["height"])
        if self._interactive:  # a service job: progress in the status bar, Esc cancels it
            return Task(lambda task: pipeline.render_job(task, settings, mesh, cam))
        # Scripts: the camera's rays in one request, the same ones the engine would trace.
        origins, directions, _, _ = camera.rays(cam)
        body = camera.ray_body(origins, directions)
        return Task(lambda task: pipeline.render(task, settings, mesh, body))

    def apply(self, context: bpy.types.Context, outcome: pipeline.Outcome) -> str:
        width, height = self._size
        build = ""
        if outcome.build is not None:
            build = "; " + _apply_build(context, outcome, self._settings)
        status = _status(context)
        status.last_upload_bytes = outcome.uploaded_bytes
        status.last_render_ms = outcome.render_ms
        status.renders += 1
        img = image.write_ao_image(outcome.ao, width, height)
        image.show_in_image_editors(context.window_manager, img)
        return f"AO {width}x{height} in {outcome.render_ms / 1e3:.1f} s{build}"


CLASSES = (
    SCENESORT_OT_server_status,
    SCENESORT_OT_server_start,
    SCENESORT_OT_server_stop,
    SCENESORT_OT_build_bvh,
    SCENESORT_OT_render_ao,
)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister() -> None:
    global _active
    if _active is not None:
        _active.cancel()
        _active = None
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
