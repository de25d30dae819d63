"""The scenesort panel, in Properties > Render and in the 3D Viewport sidebar, and the
SCENESORT engine's own Sampling and Film panels in Properties > Render."""

from __future__ import annotations

import bpy

from . import prefs, service


def _draw_service(layout: bpy.types.UILayout, status, device: str) -> None:  # noqa: ANN001
    box = layout.box()
    row = box.row()
    if status.connected:
        row.label(
            text=f"scenesort {status.version} on {status.device} at {status.url}",
            icon="CHECKMARK",
        )
    else:
        row.label(text="Not connected", icon="UNLINKED")
    row.operator("scenesort.server_status", text="", icon="FILE_REFRESH")
    settings = row.operator("preferences.addon_show", text="", icon="PREFERENCES")
    settings.module = __package__
    row = box.row(align=True)
    row.enabled = not status.busy
    if status.mismatch and service.running():
        row.alert = True
        row.operator("scenesort.server_restart", icon="FILE_REFRESH")
    else:
        row.operator("scenesort.server_start", icon="PLAY")
    stop = row.row(align=True)
    stop.enabled = service.running()
    stop.operator("scenesort.server_stop", icon="PAUSE")
    if status.connected and service.running() and status.device != device:
        row = box.row()
        row.label(text=f"Restart the service to use {device}", icon="INFO")
        row.operator("scenesort.server_restart", text="", icon="FILE_REFRESH")


def _draw_settings(layout: bpy.types.UILayout, props) -> None:  # noqa: ANN001
    col = layout.column(align=True)
    col.prop(props, "method")
    col.prop(props, "leaf_size")
    col = layout.column(align=True)
    col.prop(props, "engine")
    col.prop(props, "spp")
    col.prop(props, "target_error")
    col.prop(props, "max_pixel_error")
    col.prop(props, "use_denoising")
    col.prop(props, "ao_distance")
    col.prop(props, "seed")


def _draw_achieved(layout: bpy.types.UILayout, status) -> None:  # noqa: ANN001
    """What the last render achieved; the values' tooltips explain the units."""
    if not status.renders:
        return
    box = layout.box()
    box.label(text="Last render", icon="RENDER_RESULT")
    grid = box.grid_flow(columns=2, even_columns=True, align=True)
    grid.label(text="Est. RMSE (AO 0-1)")
    if status.last_rmse >= 0.0:
        grid.prop(status, "last_rmse", text="", emboss=False)
    else:
        grid.label(text="-")
    for name, label in (("last_spp_mean", "Mean spp"), ("last_spp_max", "Max spp"),
                        ("last_rays", "Rays")):
        grid.label(text=label)
        grid.prop(status, name, text="", emboss=False)


def _draw_timings(layout: bpy.types.UILayout, props) -> None:  # noqa: ANN001
    if not props.has_build:
        layout.label(text="No BVH built yet")
        return
    box = layout.box()
    cached = " (cached)" if props.build_cached else ""
    box.label(
        text=f"Last build: {props.build_method}, leaf {props.build_leaf_size}{cached}",
        icon="TIME",
    )
    grid = box.grid_flow(columns=2, even_columns=True, align=True)
    for name, value in (
        ("Total", f"{props.build_total_ms:.2f} ms"),
        ("MTris/s", f"{props.build_mtris_per_s:.2f}"),
        ("Triangles", f"{props.build_triangles:,}"),
        ("Nodes", f"{props.build_nodes:,}"),
        ("SAH cost", f"{props.build_sah_cost:.2f}"),
    ):
        grid.label(text=name)
        grid.label(text=value)
    for phase in props.build_phases:
        grid.label(text=f"  {phase.name}")
        grid.label(text=f"{phase.ms:.2f} ms")
    if props.build_compile_ms >= 1.0:  # Warp compiled kernels first (not in the total)
        grid.label(text="Compile (first use)")
        grid.label(text=f"{props.build_compile_ms:.0f} ms")
    if len(props.build_history):
        hist = layout.box()
        hist.label(text="Earlier builds (method, leaf, triangles, ms)")
        for record in props.build_history:
            row = hist.row()
            row.label(text=record.method)
            row.label(text=str(record.leaf_size))
            row.label(text=f"{record.triangles:,}")
            row.label(text=f"{record.total_ms:.1f}")


def draw(layout: bpy.types.UILayout, context: bpy.types.Context) -> None:
    """The whole panel; shared by both locations."""
    props = context.scene.scenesort
    status = context.window_manager.scenesort
    _draw_service(layout, status, prefs.chosen_device(prefs.preferences(context), wait=False))
    _draw_settings(layout, props)
    row = layout.row(align=True)
    row.enabled = not status.busy
    row.operator("scenesort.build_bvh", icon="MOD_BUILD")
    row.operator("scenesort.render_ao", icon="RENDER_STILL")
    if status.progress:
        layout.label(text=status.progress + "...", icon="SORTTIME")
    if status.error:
        col = layout.column(align=True)
        col.alert = True
        col.label(text=status.error, icon="ERROR")
    elif status.message:
        layout.label(text=status.message, icon="INFO")
    _draw_achieved(layout, status)
    _draw_timings(layout, props)


class SCENESORT_PT_render(bpy.types.Panel):
    bl_label = "scenesort AO"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "render"

    def draw(self, context: bpy.types.Context) -> None:
        draw(self.layout, context)


class SCENESORT_PT_view3d(bpy.types.Panel):
    bl_label = "scenesort AO"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "scenesort"

    def draw(self, context: bpy.types.Context) -> None:
        draw(self.layout, context)


class _EnginePanel:
    """A Render Properties panel of the SCENESORT engine only, as Cycles' panels are:
    `props` (an attribute path from the scene) drawn one column per group."""

    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "render"
    COMPAT_ENGINES = {"SCENESORT"}
    source = ""
    groups: tuple[tuple[tuple[str, str], ...], ...] = ()  # ((property, label), ...) per column

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return context.engine in cls.COMPAT_ENGINES

    def draw(self, context: bpy.types.Context) -> None:
        self.layout.use_property_split = True
        owner = context.scene.path_resolve(self.source)
        for group in self.groups:
            col = self.layout.column(align=True)
            for name, label in group:
                col.prop(owner, name, text=label)


class SCENESORT_PT_sampling(_EnginePanel, bpy.types.Panel):
    """Samples and the error target of F12 and animation renders."""

    bl_label = "Sampling"
    bl_order = 0
    source = "scenesort"
    groups = (
        (("spp", "Samples"), ("target_error", "Target Error"),
         ("max_pixel_error", "Max Pixel Error")),
        (("viewport_spp", "Viewport Samples"),
         ("viewport_target_error", "Viewport Target Error")),
        (("use_denoising", "Denoise"),),
        (("ao_distance", "AO Distance"), ("seed", "Seed")),
    )

    def draw(self, context: bpy.types.Context) -> None:
        _EnginePanel.draw(self, context)  # type: ignore[arg-type]
        world = context.scene.world
        if world is not None:  # what AO Distance 0 means (Cycles' panel for it is Fast GI's)
            self.layout.prop(world.light_settings, "distance", text="World AO Distance")
        device = context.window_manager.scenesort.last_device
        if device:  # the service's device, which the Device preference may have changed
            self.layout.label(text=f"Last render on {device}", icon="DESKTOP")


class SCENESORT_PT_film(_EnginePanel, bpy.types.Panel):
    """Film > Transparent: alpha is the pixel's coverage (0 on background) when on."""

    bl_label = "Film"
    bl_order = 1
    source = "render"
    groups = ((("film_transparent", "Transparent"),),)


class SCENESORT_PT_performance(_EnginePanel, bpy.types.Panel):
    """Performance > Final Render > Persistent Data, as Cycles draws it: F12 keeps the
    exported scene and reads again only what changed (persistent.py)."""

    bl_label = "Performance"
    bl_order = 2
    bl_options = {"DEFAULT_CLOSED"}
    source = "render"
    groups = ((("use_persistent_data", "Persistent Data"),),)


class SCENESORT_OBJECT_PT_ray_visibility(bpy.types.Panel):
    """Object > Visibility > Ray Visibility, as Cycles and EEVEE draw it: the two kinds
    of ray an AO render has (Mask > Holdout is Blender's own panel's)."""

    bl_label = "Ray Visibility"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "object"
    bl_parent_id = "OBJECT_PT_visibility"
    COMPAT_ENGINES = {"SCENESORT"}

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        obj = context.object
        return (context.engine in cls.COMPAT_ENGINES and obj is not None
                and obj.type in {"MESH", "CURVE", "SURFACE", "META", "FONT", "EMPTY"})

    def draw(self, context: bpy.types.Context) -> None:
        self.layout.use_property_split = True
        col = self.layout.column()
        col.prop(context.object, "visible_camera", text="Camera")
        col.prop(context.object, "visible_shadow", text="Shadow")


CLASSES = (SCENESORT_PT_sampling, SCENESORT_PT_film, SCENESORT_PT_performance,
           SCENESORT_PT_render, SCENESORT_PT_view3d, SCENESORT_OBJECT_PT_ray_visibility)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister() -> None:
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
