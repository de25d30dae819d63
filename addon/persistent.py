"""What F12 keeps between renders when Render Properties > Performance > Persistent Data
is on, as Cycles keeps its synced scene: the exported scene (flattened, or the meshes of an
instance list) with its content id, so that a later F12 of an unchanged scene reads and
hashes no mesh, and one after a change reads only what changed.

With Persistent Data Blender keeps the render depsgraph between F12s: evaluated data
stays where it was, and `depsgraph.updates` lists what changed since the last render
(measured with bpy 5.0.1: nothing after an unchanged F12 or a frame change of a still
scene, the object alone after a move, the object with its geometry after an edit or a new
modifier; everything on a depsgraph's first render). A mesh is kept while its object had
no geometry update (and, through `export.source_key`, while its evaluated data is where
it was); the flattened scene while no rendered object had one and the objects, their data,
transforms and terminator offsets are those it was made of. Without Persistent Data
Blender makes a new depsgraph for each F12, and nothing is kept.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import bpy
import numpy as np

from . import export

Layout = tuple[tuple[str, int, bytes, float, bool], ...]


@dataclass
class Kept:
    """One view layer's export, kept: an instance list's meshes, or a flattened scene."""

    meshes: export.MeshCache = field(default_factory=export.MeshCache)
    flat: export.SceneMesh | None = None
    layout: Layout = ()  # what `flat` was made of


_kept: dict[tuple[str, str], Kept] = {}  # by (scene, view layer)


def _entry(depsgraph: bpy.types.Depsgraph) -> Kept | None:
    """The view layer's kept export, what changed since the last render let go; None
    (and nothing held) without Persistent Data."""
    scene = depsgraph.scene
    key = (scene.original.name, depsgraph.view_layer.name)
    if not scene.render.use_persistent_data:
        _kept.pop(key, None)
        return None
    kept = _kept.setdefault(key, Kept())
    changed = [u.id for u in depsgraph.updates
               if u.is_updated_geometry and isinstance(u.id, bpy.types.Object)]
    for obj in changed:
        kept.meshes.forget(export.source_key(obj))
    if changed:
        kept.flat = None
    return kept


def _layout(depsgraph: bpy.types.Depsgraph) -> Layout:
    """What a flattened export is made of, read without reading a mesh."""
    return tuple((inst.object.original.name, export.source_key(inst.object),
                  np.array(inst.matrix_world, np.float64).tobytes(),
                  export.terminator_offset(inst.object), inst.is_instance)
                 for inst in export.rendered(depsgraph))


def export_scene(depsgraph: bpy.types.Depsgraph) -> export.SceneMesh:
    """`export.export_scene`, kept between F12s with Persistent Data."""
    kept = _entry(depsgraph)
    if kept is None:
        return export.export_scene(depsgraph)
    kept.meshes.clear()  # a flattened scene holds its meshes itself
    layout = _layout(depsgraph)
    if kept.flat is None or kept.layout != layout:
        kept.flat, kept.layout = export.export_scene(depsgraph), layout
    return kept.flat


def export_instances(depsgraph: bpy.types.Depsgraph) -> export.InstanceExport:
    """`export.export_instances`, its meshes kept between F12s with Persistent Data."""
    kept = _entry(depsgraph)
    if kept is None:
        return export.export_instances(depsgraph)
    kept.flat, kept.layout = None, ()
    return export.export_instances(depsgraph, kept.meshes)


def clear() -> None:
    """Let go of everything kept (the add-on is unregistered)."""
    _kept.clear()
