"""Evaluated scene (a render or viewport depsgraph) -> world-space triangles (float32
vertices, int32 indices) and, where faces are smooth-shaded, their shading normals.

Reads whole arrays with `foreach_get`; Python only loops over objects and instances,
never over vertices. Each mesh is read once and transformed per instance.

Shading normals are what Cycles renders with: each loop triangle's three corner normals
(`Mesh.corner_normals`: smooth faces, sharp edges, custom split normals), in world space;
a flat-shaded triangle has zero corners, which the engine reads as "the geometric normal"
(Cycles' `triangle_smooth_normal` falls back to it the same way). A scene without smooth
faces sends no normals at all, so its upload is what it was before normals existed.
Each object's Shadow Terminator Geometry Offset goes with its triangles when some object's
differs from Blender's default (the service's default).

`export_instances` reads the same depsgraph without flattening it: each distinct mesh once,
in its own space (a `SceneMesh` whose content hash is its id), and per instance its mesh
and 3x4 object-to-world transform: the service's instance list (docs/api.md), with each
instance's ray visibility (camera, shadow, holdout) where some differs from the default.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import bpy
import numpy as np

from . import strands
from .ao_options import AO_OPTIONS
from .client import instances_id
from .client import scene_id as content_id

# Object types whose evaluated geometry can be turned into a mesh.
_CONVERTIBLE = {"CURVE", "SURFACE", "FONT", "META"}
# Hair and points, made into tubes and spheres (strands.py).
_STRANDS = {"CURVES": strands.curve_tubes, "POINTCLOUD": strands.point_spheres}
# Geometry Cycles renders that no AO render here holds yet: counted, for the stats line.
SKIPPED_TYPES = {"VOLUME"}
# The service's (the engine's) default, Object.shadow_terminator_geometry_offset's too: a
# scene whose objects all have it sends no offsets.
DEFAULT_TERMINATOR_OFFSET = AO_OPTIONS["terminator_offset"]["default"]
# An instance's ray visibility mask, the service's bits (docs/api.md): seen by the camera,
# occluding (Cycles' AO rays are shadow rays), held out.
CAMERA, SHADOW, HOLDOUT = 1, 2, 4
DEFAULT_VISIBILITY = CAMERA | SHADOW


def terminator_offset(obj: bpy.types.Object) -> float:
    """The object's Shadow Terminator > Geometry Offset. Blender 4.5 and later keep it on
    the Object, 4.2 in Cycles' object settings (`obj.cycles`); without either (Cycles
    disabled in 4.2) Cycles' default."""
    for owner in (obj, getattr(obj, "cycles", None)):
        value = getattr(owner, "shadow_terminator_geometry_offset", None)
        if value is not None:
            return float(value)
    return DEFAULT_TERMINATOR_OFFSET


@dataclass(frozen=True)
class Span:
    """An object's loop triangles among a flattened scene's: `first` and `count` of them,
    in loop-triangle order; `mirrored`: a transform of negative determinant reversed each
    triangle's corners (corner k is the loop triangle's corner 2 - k)."""

    first: int
    count: int
    mirrored: bool


@dataclass(frozen=True)
class SceneMesh:
    """World-space triangles: vertices (N,3) float32, indices (M,3) int32; shading
    normals (M,3,3) float32 (zero corners: flat) or None when every face is flat; per
    triangle terminator offsets (M,) float32 or None when all are the default."""

    vertices: np.ndarray
    indices: np.ndarray
    objects: int  # object instances that contributed triangles
    normals: np.ndarray | None = None
    terminator_offsets: np.ndarray | None = None
    # Each real (not instanced) object's loop triangles: where a bake finds its texels'
    # triangles. Not sent.
    spans: dict[str, Span] = field(default_factory=dict, compare=False)

    @property
    def triangles(self) -> int:
        return int(self.indices.shape[0])

    @property
    def nbytes(self) -> int:
        """The length of `body()`, without making it."""
        blocks = (self.vertices, self.indices, self.normals, self.terminator_offsets)
        return sum(4 * a.size for a in blocks if a is not None)

    def body(self) -> bytes:
        """The upload body of `POST /v1/scenes`: V*3 float32, T*3 int32, then the normal
        and terminator blocks when present (`query()` says which), little-endian."""
        parts = [np.ascontiguousarray(self.vertices, dtype="<f4"),
                 np.ascontiguousarray(self.indices, dtype="<i4")]
        parts += [np.ascontiguousarray(a, dtype="<f4")
                  for a in (self.normals, self.terminator_offsets) if a is not None]
        return b"".join(a.tobytes() for a in parts)

    def query(self) -> dict[str, str]:
        """The upload's block flags (docs/api.md), only those that are on."""
        flags = {"normals": self.normals, "terminator_offsets": self.terminator_offsets}
        return {name: "true" for name, a in flags.items() if a is not None}


@dataclass(frozen=True)
class _MeshArrays:
    """One mesh in its local space: vertices (float64), loop-triangle indices, and the
    loop triangles' corner normals (float32, zero on flat ones), None when no face is
    smooth."""

    vertices: np.ndarray
    indices: np.ndarray
    normals: np.ndarray | None


_EMPTY = _MeshArrays(np.zeros((0, 3)), np.zeros((0, 3), np.int32), None)


def _source_arrays(obj: bpy.types.Object, cache: dict[int, _MeshArrays]) -> _MeshArrays:
    """The object's evaluated mesh in its own space, read once per mesh data."""
    key = obj.data.as_pointer() if obj.type == "MESH" and obj.data else obj.as_pointer()
    if key not in cache:
        if obj.type == "MESH":
            cache[key] = _mesh_arrays(obj.data)
        elif obj.type in _STRANDS:
            cache[key] = _MeshArrays(*_STRANDS[obj.type](obj.data))
        else:
            mesh = obj.to_mesh()
            try:
                cache[key] = _mesh_arrays(mesh) if mesh else _EMPTY
            finally:
                obj.to_mesh_clear()
    return cache[key]


def _mesh_arrays(mesh: bpy.types.Mesh) -> _MeshArrays:
    """Local-space vertices, loop-triangle vertex indices and corner normals of one mesh."""
    mesh.calc_loop_triangles()
    verts = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
    mesh.vertices.foreach_get("co", verts)
    count = len(mesh.loop_triangles)
    tris = np.empty(count * 3, dtype=np.int32)
    mesh.loop_triangles.foreach_get("vertices", tris)
    smooth = np.empty(count, dtype=bool)
    mesh.loop_triangles.foreach_get("use_smooth", smooth)
    normals = None
    if smooth.any():
        # The corner normals per triangle in one read: split_normals are corner_normals
        # by loop index (tests/addon/test_shading.py), read in a seventh of the time.
        normals = np.empty(count * 9, dtype=np.float32)
        mesh.loop_triangles.foreach_get("split_normals", normals)
        normals = normals.reshape(-1, 3, 3)
        normals[~smooth] = 0.0
    return _MeshArrays(verts.reshape(-1, 3).astype(np.float64), tris.reshape(-1, 3), normals)


def _world_normals(normals: np.ndarray, linear: np.ndarray) -> np.ndarray:
    """Corner normals through an object's 3x3 transform: the inverse transpose, unit
    length again (zero corners stay zero; so do all of an object scaled to nothing, whose
    triangles have no area and are never hit)."""
    if np.linalg.det(linear) == 0.0:
        return np.zeros_like(normals)
    world = normals @ np.linalg.inv(linear).astype(np.float32)  # rows: (M^-T n)^T = n^T M^-1
    length = np.linalg.norm(world, axis=-1, keepdims=True)
    return np.divide(world, length, out=np.zeros_like(world), where=length > 0.0)


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


def _object_shown(obj: bpy.types.Object, view_layer: bpy.types.ViewLayer,
                  collections: set[str], in_root: set[str]) -> bool:
    """Whether a real (non-instanced) object is visible and renderable in this view layer
    (`in_root`: the names of the scene collection's own objects)."""
    if obj.hide_render or obj.hide_viewport or not obj.visible_get(view_layer=view_layer):
        return False
    return obj.name in in_root or any(c.name in collections for c in obj.users_collection)


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
    # a set: `name in collection.objects` looks through them one by one, for every object
    in_root = set(view_layer.layer_collection.collection.objects.keys())
    shown: dict[str, bool] = {}

    def visible(obj: bpy.types.Object) -> bool:
        original = obj.original
        if original.name not in shown:
            shown[original.name] = _object_shown(original, view_layer, collections, in_root)
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
    """World-space triangles of every visible, renderable mesh-like object and instance,
    with their shading normals and terminator offsets (see the module docstring)."""
    cache: dict[int, _MeshArrays] = {}
    vertex_parts: list[np.ndarray] = []
    index_parts: list[np.ndarray] = []
    normal_parts: list[np.ndarray | None] = []
    offset_parts: list[float] = []
    spans: dict[str, Span] = {}
    offset = 0
    count = 0
    triangles = 0
    for inst in _rendered(depsgraph):
        obj = inst.object
        arrays = _source_arrays(obj, cache)
        tris, normals = arrays.indices, arrays.normals
        if len(tris) == 0:
            continue
        m = np.array(inst.matrix_world, dtype=np.float64)
        world = arrays.vertices @ m[:3, :3].T + m[:3, 3]
        normals = None if normals is None else _world_normals(normals, m[:3, :3])
        mirrored = bool(np.linalg.det(m[:3, :3]) < 0.0)
        if mirrored:
            tris = tris[:, ::-1]  # a mirroring transform flips winding; keep faces outward
            normals = None if normals is None else normals[:, ::-1]  # corners follow
        if not inst.is_instance:
            spans[obj.original.name] = Span(triangles, len(tris), mirrored)
        triangles += len(tris)
        vertex_parts.append(world.astype(np.float32))
        index_parts.append(tris + offset)
        normal_parts.append(normals)
        offset_parts.append(terminator_offset(obj))
        offset += len(arrays.vertices)
        count += 1
    if not vertex_parts:
        return SceneMesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), 0)
    indices = np.ascontiguousarray(np.concatenate(index_parts), dtype=np.int32)
    return SceneMesh(
        np.ascontiguousarray(np.concatenate(vertex_parts)),
        indices,
        count,
        *_shading(index_parts, normal_parts, offset_parts),
        spans,
    )


def _shading(index_parts: list[np.ndarray], normal_parts: list[np.ndarray | None],
             offset_parts: list[float]) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The scene's normal and terminator blocks from its instances' parts: None when no
    instance has a smooth face, and offsets None when every smooth one has the default."""
    smooth = [n is not None for n in normal_parts]
    if not any(smooth):
        return None, None
    sizes = [len(t) for t in index_parts]
    normals = np.concatenate([n if n is not None else np.zeros((size, 3, 3), np.float32)
                              for n, size in zip(normal_parts, sizes, strict=True)])
    normals = np.ascontiguousarray(normals, dtype=np.float32)
    used = {np.float32(o) for o, s in zip(offset_parts, smooth, strict=True) if s}
    if used == {np.float32(DEFAULT_TERMINATOR_OFFSET)}:
        return normals, None
    offsets = np.repeat(np.asarray(offset_parts, np.float32), sizes)
    return normals, np.ascontiguousarray(offsets, dtype=np.float32)


@dataclass(frozen=True)
class InstanceExport:
    """The scene as an instance list: `meshes` by id (first use first), each in its own
    space; instance i is `meshes[ids[mesh_index[i]]]` under `transforms[i]` (3x4 float32)."""

    meshes: dict[str, SceneMesh]
    mesh_index: np.ndarray
    transforms: np.ndarray
    visibility: np.ndarray | None = None  # (N,) uint8 masks; None: all DEFAULT_VISIBILITY
    # (N,) float32 each instance's object's Pass Index (the Object Index pass); not sent
    pass_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32),
                                   compare=False)

    @property
    def triangles(self) -> int:
        """Triangles the instances stand for (what the flattened scene would hold)."""
        counts = np.array([m.triangles for m in self.meshes.values()], np.int64)
        return int(counts[self.mesh_index].sum()) if len(self.mesh_index) else 0

    @property
    def objects(self) -> int:
        return len(self.mesh_index)

    @property
    def holdouts(self) -> bool:
        """Whether the camera may see a holdout (the job then has a holdout image)."""
        return self.visibility is not None and bool(
            np.any((self.visibility & CAMERA != 0) & (self.visibility & HOLDOUT != 0)))

    def body(self) -> bytes:
        """The body of `POST /v1/instance-scenes`: K*32 hex ids, N int32, N*12 float32,
        then N uint8 masks when `visibility` (its `visibility=true`)."""
        ids = "".join(self.meshes).encode("ascii")
        masks = b"" if self.visibility is None else self.visibility.astype(np.uint8).tobytes()
        return (ids + np.ascontiguousarray(self.mesh_index, "<i4").tobytes()
                + np.ascontiguousarray(self.transforms, "<f4").tobytes() + masks)

    @property
    def scene_id(self) -> str:
        return instances_id(len(self.meshes), len(self.mesh_index), self.body())


def _local_mesh(arrays: _MeshArrays, terminator_offset: float) -> SceneMesh:
    """One mesh in its own space; the object's terminator offset goes with its smooth
    triangles when it is not the default (it is then part of the mesh's content)."""
    offsets = None
    if arrays.normals is not None and (
            np.float32(terminator_offset) != np.float32(DEFAULT_TERMINATOR_OFFSET)):
        offsets = np.full(len(arrays.indices), terminator_offset, np.float32)
    return SceneMesh(np.ascontiguousarray(arrays.vertices, np.float32),
                     np.ascontiguousarray(arrays.indices, np.int32), 1, arrays.normals, offsets)


def mesh_id(mesh: SceneMesh) -> str:
    """The service's id of a mesh: the content hash of its upload body."""
    return content_id(len(mesh.vertices), mesh.triangles, mesh.body())


def ray_visibility(inst: bpy.types.DepsgraphObjectInstance, view_layer: bpy.types.ViewLayer,
                   ) -> int:
    """The instance's mask as Cycles reads it: Ray Visibility > Camera and Shadow of its
    object and, for an instance, of its instancer too; holdout (the object's Mask >
    Holdout or a holdout collection) of the instancer, else of the object."""
    obj = inst.object
    owner = inst.parent if inst.is_instance and inst.parent is not None else obj
    mask = 0
    if obj.visible_camera and owner.visible_camera:
        mask |= CAMERA
    if obj.visible_shadow and owner.visible_shadow:
        mask |= SHADOW
    if owner.original.holdout_get(view_layer=view_layer):
        mask |= HOLDOUT
    return mask


def _rendered(depsgraph: bpy.types.Depsgraph,
              ) -> Iterator[bpy.types.DepsgraphObjectInstance]:
    """`_instances` that have mesh-like geometry (hair and points included)."""
    for inst in _instances(depsgraph):
        kind = inst.object.type
        if kind == "MESH" or kind in _CONVERTIBLE or kind in _STRANDS:
            yield inst


def skipped(depsgraph: bpy.types.Depsgraph) -> dict[str, int]:
    """What renders in Cycles but not here, counted by kind: volumes, and particle hair
    (HAIR particle systems shown for rendering)."""
    counts: dict[str, int] = {}
    for inst in _instances(depsgraph):
        obj = inst.object
        if obj.type in SKIPPED_TYPES:
            counts[obj.type.lower()] = counts.get(obj.type.lower(), 0) + 1
        hair = sum(1 for p in getattr(obj, "particle_systems", ())
                   if p.settings.type == "HAIR" and p.settings.render_type == "PATH")
        if hair and not inst.is_instance:
            counts["particle hair"] = counts.get("particle hair", 0) + hair
    return counts


def custom_visibility(depsgraph: bpy.types.Depsgraph) -> bool:
    """Whether some object's ray visibility or holdout is not the default."""
    view_layer = depsgraph.view_layer
    return any(ray_visibility(inst, view_layer) != DEFAULT_VISIBILITY
               for inst in _rendered(depsgraph))


def has_instances(depsgraph: bpy.types.Depsgraph) -> bool:
    """Whether the scene renders best as an instance list: some geometry is instanced
    (collection instances, instancing by vertices or faces, geometry nodes), mesh data is
    shared by several objects, or an object's ray visibility or holdout is not the
    default (only an instance list carries them). Reads no mesh."""
    view_layer = depsgraph.view_layer
    seen: set[int] = set()
    for inst in _rendered(depsgraph):
        obj = inst.object
        data = obj.data.as_pointer() if obj.type == "MESH" and obj.data else None
        if inst.is_instance or data in seen or ray_visibility(
                inst, view_layer) != DEFAULT_VISIBILITY:
            return True
        if data is not None:
            seen.add(data)
    return False


@dataclass
class MeshCache:
    """Meshes read by `export_instances`, kept between exports of one depsgraph whose
    geometry did not change (the Rendered viewport after moving objects: its evaluated
    meshes stay where they were): the arrays by evaluated data, and each (arrays,
    terminator offset)'s local mesh and id. Clear it after any geometry update."""

    arrays: dict[int, _MeshArrays] = field(default_factory=dict)
    local: dict[tuple[int, float], tuple[str, SceneMesh]] = field(default_factory=dict)

    def clear(self) -> None:
        self.arrays.clear()
        self.local.clear()


def export_instances(depsgraph: bpy.types.Depsgraph,
                     cache: MeshCache | None = None) -> InstanceExport:
    """What `export_scene` renders, as meshes and instances: instanced meshes are read and
    hashed once, not expanded (nor again while `cache` holds them); instances scaled to
    nothing (no area) are left out; each instance's `ray_visibility`."""
    cache = MeshCache() if cache is None else cache
    local = cache.local
    meshes: dict[str, SceneMesh] = {}
    position: dict[str, int] = {}  # mesh id -> its place in `meshes`
    index: list[int] = []
    transforms: list[np.ndarray] = []
    masks: list[int] = []
    pass_index: list[int] = []
    view_layer = depsgraph.view_layer
    for inst in _rendered(depsgraph):
        obj = inst.object
        arrays = _source_arrays(obj, cache.arrays)
        if len(arrays.indices) == 0:
            continue
        key = (id(arrays), terminator_offset(obj))
        if key not in local:
            mesh = _local_mesh(arrays, key[1])
            local[key] = (mesh_id(mesh), mesh)
        name, mesh = local[key]
        if name not in meshes:
            position[name] = len(meshes)
            meshes[name] = mesh
        index.append(position[name])
        transforms.append(np.array(inst.matrix_world, dtype=np.float32)[:3])
        masks.append(ray_visibility(inst, view_layer))
        pass_index.append(obj.pass_index)
    placed = np.asarray(transforms, np.float32).reshape(-1, 3, 4)
    # instances scaled to nothing have no area (and no inverse for the service)
    keep = np.linalg.det(placed[:, :, :3].astype(np.float64)) != 0.0
    visibility = np.asarray(masks, np.uint8)[keep]
    used = np.unique(np.asarray(index, np.int32)[keep])
    if len(used) < len(meshes):  # a mesh only under such instances is not sent
        names = list(meshes)
        meshes = {names[k]: meshes[names[k]] for k in used}
        renumber = np.full(len(names), -1, np.int32)
        renumber[used] = np.arange(len(used), dtype=np.int32)
        index = renumber[np.asarray(index, np.int32)].tolist()
    return InstanceExport(
        meshes,
        np.asarray(index, np.int32)[keep],
        placed[keep],
        None if (visibility == DEFAULT_VISIBILITY).all() else visibility,
        np.asarray(pass_index, np.float32)[keep],
    )
