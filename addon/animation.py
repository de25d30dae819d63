"""File > Export > scenesort animation: the scene's frame range as a frame bundle, which
`scenesort render-frames BUNDLE --out DIR` renders without Blender.

The layout is backend/render/bundle.py's (docs/api.md, "Frame bundles"): each distinct mesh once,
in its own space and named by its content hash (a deformed mesh is a new one in the frames
where it changed), per frame the camera and the instance list, and the render settings
in the manifest. Instances come from the depsgraph's object instances without expanding
them (`export.export_instances`). The current frame is set back afterwards.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import bpy
from bpy.props import StringProperty

from . import camera, export, pipeline

FORMAT = "scenesort-frame-bundle"  # backend/render/bundle.py reads this format and version
VERSION = 1


@dataclass(frozen=True)
class Written:
    """What an export wrote: frames, distinct meshes, and the bytes of the mesh files."""

    frames: int
    meshes: int
    mesh_bytes: int


def _frame_stem(root: Path, frame: int) -> Path:
    return root / "frames" / f"{frame:06d}"


def write_bundle(context: bpy.types.Context, directory: str | Path) -> Written:
    """Export the scene's frame range (start, end, step) into `directory`."""
    scene = context.scene
    root = Path(bpy.path.abspath(str(directory)))
    frames = list(range(scene.frame_start, scene.frame_end + 1, max(1, scene.frame_step)))
    # The bundle traces with the BVH engine: instance lists are BVH scenes.
    settings = {k: v for k, v in pipeline.job_fields(pipeline.Settings.from_scene(scene)).items()
                if k != "engine"}
    (root / "meshes").mkdir(parents=True, exist_ok=True)
    (root / "frames").mkdir(exist_ok=True)
    meshes: dict[str, dict[str, Any]] = {}
    mesh_bytes = 0
    current = (scene.frame_current, scene.frame_subframe)
    try:
        for frame in frames:
            scene.frame_set(frame)
            depsgraph = context.evaluated_depsgraph_get()
            view = camera.view(scene, depsgraph)
            listing = export.export_instances(depsgraph)
            if listing.triangles == 0:
                raise ValueError(f"Frame {frame} has no visible, renderable mesh triangles")
            for mesh_id, mesh in listing.meshes.items():
                if mesh_id in meshes:
                    continue
                body = mesh.body()
                path = root / "meshes" / f"{mesh_id}.bin"
                if not path.exists() or path.stat().st_size != len(body):
                    path.write_bytes(body)  # same name, same bytes: a content hash
                mesh_bytes += len(body)
                meshes[mesh_id] = {"vertices": len(mesh.vertices), "triangles": mesh.triangles,
                                   "normals": mesh.normals is not None,
                                   "terminator_offsets": mesh.terminator_offsets is not None}
            stem = _frame_stem(root, frame)
            stem.with_suffix(".bin").write_bytes(listing.body())
            record = {"frame": frame, **view, "meshes": len(listing.meshes),
                      "instances": listing.objects,
                      "visibility": listing.visibility is not None}
            stem.with_suffix(".json").write_text(json.dumps(record, indent=1))
    finally:
        scene.frame_set(current[0], subframe=current[1])
    manifest = {"format": FORMAT, "version": VERSION, "frames": frames, "settings": settings,
                "meshes": meshes}
    # Last: a bundle whose export failed half-way has no (new) manifest to be read.
    (root / "manifest.json").write_text(json.dumps(manifest, indent=1))
    return Written(len(frames), len(meshes), mesh_bytes)


class SCENESORT_OT_export_animation(bpy.types.Operator):
    """Write the scene's frame range as a scenesort frame bundle (meshes once, instances
    and cameras per frame) for `scenesort render-frames`"""

    bl_idname = "scenesort.export_animation"
    bl_label = "Export scenesort Animation"
    bl_options = {"REGISTER"}

    directory: StringProperty(  # type: ignore[valid-type]
        name="Folder", description="The bundle's folder (created if missing)",
        subtype="DIR_PATH",
    )

    def invoke(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context: bpy.types.Context) -> set[str]:
        if not self.directory:
            self.report({"ERROR"}, "Choose the folder to write the bundle into")
            return {"CANCELLED"}
        try:
            written = write_bundle(context, self.directory)
        except (ValueError, OSError) as exc:
            self.report({"ERROR"}, f"scenesort: {exc}")
            return {"CANCELLED"}
        self.report({"INFO"}, f"scenesort: {written.frames} frames, {written.meshes} meshes "
                              f"({written.mesh_bytes / 1e6:.1f} MB) in {self.directory}")
        return {"FINISHED"}


def _menu(self: Any, context: bpy.types.Context) -> None:
    self.layout.operator(SCENESORT_OT_export_animation.bl_idname, text="scenesort animation")


def register() -> None:
    bpy.utils.register_class(SCENESORT_OT_export_animation)
    bpy.types.TOPBAR_MT_file_export.append(_menu)


def unregister() -> None:
    bpy.types.TOPBAR_MT_file_export.remove(_menu)
    bpy.utils.unregister_class(SCENESORT_OT_export_animation)
