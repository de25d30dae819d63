"""Evaluated scene (a render or viewport depsgraph) -> world-space triangles (float32
vertices, int32 indices).

Reads whole arrays with `foreach_get`; Python only loops over objects and instances,
never over vertices. Each mesh is read once and transformed per instance.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import bpy
import numpy as np

# Object types whose evaluated geometry can be turned into a mesh.
_CONVERTIBLE = {"CURVE", "SURFACE", "FONT", "META"}
_EMPTY = (np.zeros((0, 3)), np.zeros((0, 3), np.int32))


@dataclass(frozen=True)
class SceneMesh:
    """World-space triangles: vertices (N,3) float32, indices (M,3) int32."""

    vertices: np.ndarray
    indices: np.ndarray
    objects: int  # object instances that contributed triangles

    @property
    def triangles(self) -> int:
        return int(self.indices.shape[0])

    def body(self) -> bytes:
        """The upload body of `POST /v1/scenes`: V*3 float32 then T*3 int32, little-endian."""
        return (
            np.ascontiguousarray(self.vertices, dtype="<f4").tobytes()
            + np.ascontiguousarray(self.indices, dtype="<i4").tobytes()
        )


def _mesh_arrays(mesh: bpy.types.Mesh) -> tuple[np.ndarray, np.ndarray]:
    """Local-space vertices (float64) and loop-triangle vertex indices of one mesh."""
    mesh.calc_loop_triangles()
    verts = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
    mesh.vertices.foreach_get("co", verts)
    tris = np.empty(len(mesh.loop_triangles) * 3, dtype=np.int32)
    mesh.loop_triangles.foreach_get("vertices", tris)
    return verts.reshape(-1, 3).astype(np.float64), tris.reshape(-1, 3)


def _renderable_collections(view_layer: bpy.types.ViewLayer) -> set[str]:
    """Names of collections that are included, shown and enabled for rendering."""
    names: set[str] = set()

    def walk(layer_collection: bpy.types.LayerCollection) -> None:
        for child in layer_collection.children:
            if child.exclude or child.hide_viewport:
                continue
            coll = child.collection
            if coll.hide_render or coll.hide_viewport:
                continue
            names.add(coll.name)
            walk(child)

    walk(view_layer.layer_collection)
    names.add(view_layer.layer_collection.collection.name)  # the scene collection
    return names


def _object_shown(
    obj: bpy.types.Object, view_layer: bpy.types.ViewLayer, collections: set[str]
) -> bool:
    """Whether a real (non-instanced) object is visible and renderable in this view layer."""
    if obj.hide_render or obj.hide_viewport or not obj.visible_get(view_layer=view_layer):
        return False
    scene_collection = view_layer.layer_collection.collection
    in_scene_root = obj.name in scene_collection.objects
    return in_scene_root or any(c.name in collections for c in obj.users_collection)


def _instances(depsgraph: bpy.types.Depsgraph) -> Iterator[bpy.types.DepsgraphObjectInstance]:
    """Depsgraph instances that render: shown objects and their instances.

    A render depsgraph (the engine's, what F12 renders) already holds only what renders:
    objects and collections enabled for rendering, excluded collections left out,
    modifiers at their render levels, whatever the viewport shows. A viewport depsgraph
    (the panel's quick look) holds the render-disabled ones too, so they are filtered here.
    """
    if depsgraph.mode == "RENDER":
        for inst in depsgraph.object_instances:
            if inst.show_self and not (inst.is_instance and inst.object.original.hide_render):
                yield inst
        return
    view_layer = depsgraph.view_layer  # the original view layer, with the user's switches
    collections = _renderable_collections(view_layer)
    shown: dict[str, bool] = {}

    def visible(obj: bpy.types.Object) -> bool:
        original = obj.original
        if original.name not in shown:
            shown[original.name] = _object_shown(original, view_layer, collections)
        return shown[original.name]

    for inst in depsgraph.object_instances:
        if inst.is_instance:
            # Instances follow their instancer's visibility; the instanced objects'
            # own render switch still applies (as in Cycles).
            if not visible(inst.parent) or inst.object.original.hide_render:
                continue
        elif not inst.show_self or not visible(inst.object):
            continue
        yield inst


def export_scene(depsgraph: bpy.types.Depsgraph) -> SceneMesh:
    """World-space triangles of every visible, renderable mesh-like object and instance."""
    cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    vertex_parts: list[np.ndarray] = []
    index_parts: list[np.ndarray] = []
    offset = 0
    count = 0
    for inst in _instances(depsgraph):
        obj = inst.object
        if obj.type != "MESH" and obj.type not in _CONVERTIBLE:
            continue
        key = obj.data.as_pointer() if obj.type == "MESH" and obj.data else obj.as_pointer()
        if key not in cache:
            if obj.type == "MESH":
                cache[key] = _mesh_arrays(obj.data)
            else:
                mesh = obj.to_mesh()
                try:
                    cache[key] = _mesh_arrays(mesh) if mesh else _EMPTY
                finally:
                    obj.to_mesh_clear()
        local, tris = cache[key]
        if len(tris) == 0:
            continue
        m = np.array(inst.matrix_world, dtype=np.float64)
        world = local @ m[:3, :3].T + m[:3, 3]
        if np.linalg.det(m[:3, :3]) < 0.0:
            tris = tris[:, ::-1]  # a mirroring transform flips winding; keep faces outward
        vertex_parts.append(world.astype(np.float32))
        index_parts.append(tris + offset)
        offset += len(local)
        count += 1
    if not vertex_parts:
        return SceneMesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), 0)
    return SceneMesh(
        np.ascontiguousarray(np.concatenate(vertex_parts)),
        np.ascontiguousarray(np.concatenate(index_parts), dtype=np.int32),
        count,
    )
