"""The `scenesort AO` render engine: F12 and animation renders through the service.

Blender calls `render(depsgraph)` once per frame and view layer with the RENDER
depsgraph (render visibility, modifiers at render levels), on its render thread (the
main thread when headless). The work is the one render path, `pipeline.render_job`, on
a worker thread, while this thread polls `test_break()` (Esc cancels the service's job)
and shows the step in the status bar. Blender writes the files of Ctrl-F12 itself.

Frame ranges (Ctrl-F12) with the BVH engine send the scene as an instance list
(`export.export_instances`): per frame each mesh is asked for by its hash (HEAD) and sent
only when the service lacks it, and the list of instances is sent when it changed; the
service then builds only what changed (backend/render/bvhs.py). F12 does the same when the
scene has instances, ray visibility or holdouts, or an Object or Material Index pass (what
only an instance list carries), else sends the flattened scene. With Persistent Data on (Render
Properties > Performance) the export is kept between F12s and only what changed is read
again (persistent.py). The Rendered viewport's
`view_update`/`view_draw` hand the work to a `viewport.ViewSession`.

Passes, as Cycles writes them: Combined RGB = AO and 0 where the camera ray missed,
alpha = coverage with Film > Transparent and 1 without; and those the view layer turns on
(`image.OPTIONAL_PASSES`): `AO` (one channel, 0 on background), `Depth` (camera-space Z,
1e10 on background; traced only when on), Normal, Position, Object and Material Index and
the Denoising Normal, Albedo and Depth of Cycles' Denoising Data, so that the compositor's
Denoise node works.
"""

from __future__ import annotations

import threading
import time
import traceback
from collections.abc import Callable
from typing import Any

import bpy
import numpy as np

from . import (
    bake,
    camera,
    export,
    image,
    persistent,
    pipeline,
    prefs,
    service,
    timings,
    viewport,
)
from .client import ServiceError
from .tasks import Cancelled, Task

POLL_S = 0.05
CANCEL_WAIT_S = 0.3  # Esc gives control back this soon, whatever the worker is waiting on
PASSES = (("Combined", 4, "RGBA", "COLOR"),)  # always; the others as the view layer says
_EXPECTED = (ServiceError, service.LaunchError, ValueError)


def stats_line(outcome: pipeline.Outcome, triangles: int) -> str:
    """Build and trace times, the scene's size, what the render achieved (estimated
    RMSE in AO units, mean and largest spp, rays) and the device that traced it, for the
    status bar and metadata."""
    build = outcome.build or {}
    build_ms = float((build.get("timings_ms") or {}).get("total", 0.0))
    cached = " (cached)" if build.get("cached") else ""
    trace_ms = outcome.timings_ms.get("ao", 0.0)
    rmse = "-" if outcome.rmse_estimate is None else f"{outcome.rmse_estimate:.4f}"
    report = outcome.build_report
    if report is not None:  # an instance list: what the frame built
        kinds = {k: len(report[k]) for k in ("built", "refit", "reused") if report[k]}
        meshes = ", ".join(f"{n} {k}" for k, n in kinds.items()) or "none"
        build_ms = sum(float(v) for v in (report.get("timings_ms") or {}).values())
        cached = f" (meshes {meshes}; top level {report['top_level']})"
    if outcome.denoised:
        rmse += " before denoising"
    return (
        f"{triangles:,} triangles | build {build_ms:.1f} ms{cached} | "
        f"trace {trace_ms:.1f} ms | total {outcome.render_ms:.0f} ms | "
        f"est. RMSE {rmse} | spp {outcome.spp_mean:.1f} mean, {outcome.spp_max} max | "
        f"{outcome.rays:,} rays | film {outcome.film or '-'} | {outcome.device}"
    )


class AoEngine:
    """What the engine does; a mixin, so that a subclass can register as an engine of
    its own (Blender maps one registered class to one RNA type).

    Blender's own methods (test_break, update_stats, end_result) cannot be overridden
    from Python, so the engine reaches them through `stopped`, `show` and `fill`.
    """

    task: Task | None = None  # the running render's work

    def stopped(self) -> bool:
        """Whether the user pressed Esc."""
        return self.test_break()

    def show(self, text: str) -> None:
        """A line in the status bar (and the render window's header)."""
        self.update_stats("", f"scenesort: {text}")

    def fill(self, result: bpy.types.RenderResult, passes: dict[str, np.ndarray]) -> None:
        """Write `passes` into the Render Result's layer (`foreach_set` on the flat buffer:
        measured 0.3 ms for 320x240 RGBA, where assigning `rect` takes 90 ms)."""
        layer = result.layers[0]
        for name, pixels in passes.items():
            found = layer.passes.get(name)
            if found is not None:  # a pass the view layer turned off is not in the result
                found.rect.foreach_set(np.ascontiguousarray(pixels, np.float32).ravel())

    def update_render_passes(self, scene: Any = None, renderlayer: Any = None) -> None:
        for name, channels, chan_id, kind in PASSES:
            self.register_pass(scene, renderlayer, name, channels, chan_id, kind)
        for extra in image.wanted_passes(renderlayer):
            self.register_pass(scene, renderlayer, *extra.blender)

    def render(self, depsgraph: bpy.types.Depsgraph) -> None:
        self._guarded("Render", lambda: self._render(depsgraph))

    # --- the Rendered viewport (viewport.py does the work) ----------------------------

    view_session: viewport.ViewSession | None = None

    def view_update(self, context: bpy.types.Context, depsgraph: bpy.types.Depsgraph) -> None:
        """Blender's call after a change: the session reads what changed and restarts."""
        first = self.view_session is None
        if first:
            self.view_session = viewport.ViewSession(prefs.target(context))
        self.view_session.update_scene(depsgraph, first)

    def view_draw(self, context: bpy.types.Context, depsgraph: bpy.types.Depsgraph) -> None:
        """Blender's call to draw the region: the latest round's image, and another redraw
        while the rounds go on."""
        session = self.view_session
        if session is None:
            return
        region, space = context.region, context.region_data
        scale = context.preferences.system.pixel_size
        try:
            session.look(viewport.region_view(space.view_matrix, space.window_matrix,
                                              region.width, region.height,
                                              viewport.pixel_size(depsgraph.scene, scale)))
        except ValueError as exc:
            session.error = str(exc)
        frame = session.frame()
        if frame is not None:
            self.bind_display_space_shader(depsgraph.scene)
            viewport.draw_frame(frame, region.width, region.height)
            self.unbind_display_space_shader()
        self.update_stats("", viewport.status_text(session))
        if session.refining:
            self.tag_redraw()

    def __del__(self) -> None:
        try:
            session = self.view_session
        except ReferenceError:  # Blender already freed the engine's data
            return
        if session is not None:
            session.stop()

    def bake(self, depsgraph: bpy.types.Depsgraph, obj: bpy.types.Object, pass_type: str,
             pass_filter: int, width: int, height: int) -> None:
        """Blender's Bake of `obj` (image textures or colour attributes; see bake.py). Blender
        writes the result whatever happened (its RE_bake_engine cannot fail): after Esc or
        an error the covered texels get 0, as they would from Cycles stopped early."""
        self._guarded("Bake", lambda: self._bake(depsgraph, obj, pass_type, width, height))

    def _guarded(self, what: str, work: Callable[[], None]) -> None:
        """`work`, its failures reported in words, never a traceback."""
        try:
            work()
        except Cancelled:
            self._say("INFO", f"{what} cancelled; the service stops its job (a BVH build "
                              "under way ends and is kept for the next render)")
        except Exception as exc:  # noqa: BLE001 - reported in words, never a traceback
            message = str(exc)
            if not isinstance(exc, _EXPECTED):  # a bug: the console gets the traceback
                traceback.print_exception(exc)
                message = f"Unexpected error ({type(exc).__name__}: {exc}); see the console"
            self._say("ERROR", message)

    def _render(self, depsgraph: bpy.types.Depsgraph) -> None:
        scene = depsgraph.scene
        transparent = scene.render.film_transparent
        view = camera.view(scene, depsgraph, self.camera_override)
        self.show("exporting the scene")
        # Instance lists for the BVH engine where they pay (instances, shared meshes) or
        # carry what a flattened scene cannot (ray visibility, holdout); every frame of an
        # animation, so that unchanged meshes are never sent twice.
        extras = image.wanted_passes(depsgraph.view_layer)
        instanced = scene.scenesort.engine == "bvh" and (
            self.is_animation or export.has_instances(depsgraph)
            or any(extra.per_object for extra in extras))
        mesh = (persistent.export_instances if instanced else persistent.export_scene)(depsgraph)
        if not instanced and export.custom_visibility(depsgraph):
            self._say("WARNING", "Ray visibility and holdout are ignored by the DACRT engine: "
                                 "choose the BVH engine to honour them")
        if mesh.triangles == 0:
            frame = view["window"] or view["camera"]
            size = (frame["width"], frame["height"])
            self._write(depsgraph, image.empty_passes(*size, transparent), size)
            self._say(
                "WARNING",
                "Nothing to render: no object with mesh triangles is "
                "enabled for rendering; the image is empty",
            )
            return
        settings = pipeline.Settings.from_scene(scene)
        target = prefs.target(bpy.context)
        outcome = self._run(
            lambda task: pipeline.render_job(task, target, settings, mesh, view,
                                             image.service_passes(extras),
                                             image.needs_depth(extras)),
            f"{mesh.triangles:,} triangles",
        )
        line = stats_line(outcome, mesh.triangles)
        missing = export.skipped(depsgraph)
        if missing:  # what Cycles would show and this render does not
            line += " | not rendered: " + ", ".join(f"{n} {kind}" for kind, n in missing.items())
        passes = image.result_passes(outcome, transparent)
        passes.update(image.extra_passes(outcome, extras, mesh))
        self._write(depsgraph, passes, outcome.size, line)
        self.show(line)
        self._keep(scene, outcome)

    def _bake(self, depsgraph: bpy.types.Depsgraph, obj: bpy.types.Object, pass_type: str,
              width: int, height: int) -> None:
        refused = bake.refusal(pass_type)
        if refused:
            raise ValueError(refused)
        scene = depsgraph.scene
        if self._baked_scene is None:  # once per object, whatever its images
            self.show("exporting the scene")
            self._baked_scene = export.export_scene(depsgraph)
        mesh = self._baked_scene
        span = mesh.spans.get(obj.original.name)
        if span is None:
            raise ValueError(f"'{obj.original.name}' does not render (disabled for rendering "
                             "or hidden), so it has no triangles to bake: enable it for "
                             "rendering")
        result = self.begin_result(0, 0, width, height, layer=self._bake_layer(), view="")
        try:
            primitive = np.empty(width * height * 3, np.float32)
            result.layers[0].passes["BakePrimitive"].rect.foreach_get(primitive)
            texels, triangles, u, v = bake.texel_points(primitive.reshape(-1, 3), span)
            if pass_type == bake.NORMAL:
                values = bake.texel_normals(mesh, triangles, u, v)
            else:
                settings = pipeline.Settings.from_scene(scene)
                target = prefs.target(bpy.context)
                outcome = self._run(
                    lambda task: pipeline.bake_job(task, target, settings, mesh, triangles,
                                                   u, v),  # fmt: skip
                    f"{len(texels):,} texels of '{obj.original.name}'",
                )
                values = outcome.ao
            self.fill(result, {"Combined": bake.combined(values, texels, width * height)})
        except BaseException:
            self.end_result(result, cancel=True)
            raise
        self.end_result(result)
        if pass_type == bake.NORMAL:
            self._say("INFO", f"baked the normals of {len(texels):,} texels of "
                              f"'{obj.original.name}'")  # fmt: skip
            bent = bake.bent_normal_materials(obj.original)
            if bent:
                self._say("WARNING", f"the Normal bake ignores the Bump and Normal Map nodes "
                                     f"of {', '.join(bent)}: bake with Cycles to include "
                                     "them")  # fmt: skip
            return
        self._say("INFO", f"baked {len(texels):,} texels of '{obj.original.name}' | "
                          + stats_line(outcome, mesh.triangles))  # fmt: skip
        self._keep(scene, outcome)

    # --- steps ----------------------------------------------------------------------

    # Of this engine instance: Blender makes one per baked object and calls `bake` once
    # per image of it.
    _images_baked = 0
    _baked_scene: export.SceneMesh | None = None

    def _bake_layer(self) -> str:
        """A layer name of its own for each image of the object (Blender calls `bake` once
        per image, UDIM tile or colour attribute, and files each result under the first
        image whose layer has that name)."""
        self._images_baked += 1
        return f"scenesort bake {self._images_baked}"

    def _run(self, work: Callable[[Task], pipeline.Outcome], what: str) -> pipeline.Outcome:
        """`work` on a worker thread while this one polls Esc and shows progress. After
        Esc, control comes back within CANCEL_WAIT_S: a request that cannot be cut short
        (a BVH build) is left to end on the worker, which then stops (it only talks to
        the service: the scene was read on this thread)."""
        self.task = Task(work)
        self.task.start()
        cancelled_at = None
        while not self.task.done:
            if cancelled_at is None and self.stopped():
                self.task.cancel()
                cancelled_at = time.perf_counter()
            if cancelled_at is not None and time.perf_counter() - cancelled_at > CANCEL_WAIT_S:
                raise Cancelled()
            self.update_progress(self.task.fraction)
            self.show(f"{self.task.step} ({what})")
            self.task.join(POLL_S)  # back as the work ends, not up to POLL_S after it
        if self.task.error is not None:
            raise self.task.error
        return self.task.result

    def _write(
        self,
        depsgraph: bpy.types.Depsgraph,
        passes: dict[str, np.ndarray],
        size: tuple[int, int],
        note: str = "",
    ) -> None:
        """Fill the Render Result (the border's size when there is one) with `passes`;
        `note` goes to the result's metadata."""
        width, height = size
        result = self.begin_result(0, 0, width, height, layer=depsgraph.view_layer.name)
        if (result.resolution_x, result.resolution_y) != size:
            self.end_result(result, cancel=True)
            raise ValueError(
                f"Blender's render result is {result.resolution_x}x{result.resolution_y}, "
                f"the service rendered {width}x{height}"
            )
        self.fill(result, passes)
        self.end_result(result)
        if note:  # on the whole render's result, as Cycles does: files carry it
            self.get_result().stamp_data_add_field("scenesort", note)

    def _keep(self, scene: bpy.types.Scene, outcome: pipeline.Outcome) -> None:
        """What the render or bake achieved (the panel's Last render box, the Sampling
        panel's device) and the build's timings for the panel's table, on the main
        thread."""
        props, settings = scene.original.scenesort, pipeline.Settings.from_scene(scene)

        def apply() -> None:
            pipeline.remember(bpy.context.window_manager.scenesort, outcome)
            if outcome.build is not None:
                timings.apply_build(props, outcome.build, settings.method, settings.leaf_size)

        if threading.current_thread() is threading.main_thread():
            apply()
        else:  # Blender data is written on the main thread only
            bpy.app.timers.register(apply, first_interval=0.0)

    def _say(self, level: str, message: str) -> None:
        self.report({level}, f"scenesort: {message}")
        self.show(message)


class SCENESORT_RE_ao(AoEngine, bpy.types.RenderEngine):
    """Ambient occlusion from the scenesort service, like Cycles' AO pass."""

    bl_idname = "SCENESORT"
    bl_label = "scenesort AO"
    bl_use_preview = False


# Cycles' Bake panel and its sub-panels (bake type, Selected to Active, output, margin):
# Blender's bake settings, which the engine's bake reads as Cycles' does. (Influence is
# for Combined and lighting passes, which this engine does not bake.)
BAKE_PANELS = ("CYCLES_RENDER_PT_bake", "CYCLES_RENDER_PT_bake_selected_to_active",
               "CYCLES_RENDER_PT_bake_output", "CYCLES_RENDER_PT_bake_output_margin")


def _compatible_panels() -> list[type]:
    """Blender's panels that work with any engine (output, format, color management...),
    as Blender's render-engine template finds them, and Cycles' Bake panels."""
    found = [
        panel
        for panel in bpy.types.Panel.__subclasses__()
        if "BLENDER_RENDER" in getattr(panel, "COMPAT_ENGINES", ())
    ]
    return found + [p for p in (getattr(bpy.types, n, None) for n in BAKE_PANELS) if p]


_added_to: list[type] = []


def register() -> None:
    bpy.utils.register_class(SCENESORT_RE_ao)
    for panel in _compatible_panels():
        if SCENESORT_RE_ao.bl_idname not in panel.COMPAT_ENGINES:
            panel.COMPAT_ENGINES.add(SCENESORT_RE_ao.bl_idname)
            _added_to.append(panel)


def unregister() -> None:
    for panel in _added_to:
        panel.COMPAT_ENGINES.discard(SCENESORT_RE_ao.bl_idname)
    _added_to.clear()
    persistent.clear()
    bpy.utils.unregister_class(SCENESORT_RE_ao)
