"""The scenesort panel, in Properties > Render and in the 3D Viewport sidebar."""

from __future__ import annotations

import bpy

from . import service


def _draw_service(layout: bpy.types.UILayout, props, status) -> None:  # noqa: ANN001
    box = layout.box()
    box.prop(props, "server_url")
    row = box.row()
    if status.connected:
        row.label(text=f"Connected: {status.version} on {status.device}", icon="CHECKMARK")
    else:
        row.label(text="Not connected", icon="UNLINKED")
    row.operator("scenesort.server_status", text="", icon="FILE_REFRESH")
    row = box.row(align=True)
    row.operator("scenesort.server_start", icon="PLAY")
    stop = row.row(align=True)
    stop.enabled = service.running()
    stop.operator("scenesort.server_stop", icon="PAUSE")


def _draw_settings(layout: bpy.types.UILayout, props) -> None:  # noqa: ANN001
    col = layout.column(align=True)
    col.prop(props, "method")
    col.prop(props, "leaf_size")
    col = layout.column(align=True)
    col.prop(props, "engine")
    col.prop(props, "spp")
    col.prop(props, "target_error")
    col.prop(props, "ao_distance")
    col.prop(props, "seed")


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
    _draw_service(layout, props, status)
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


CLASSES = (SCENESORT_PT_render, SCENESORT_PT_view3d)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister() -> None:
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
