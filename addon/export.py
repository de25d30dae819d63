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
from functools import cached_property

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

    def blocks(self) -> list[memoryview]:
        """The upload body of `POST /v1/scenes` as its blocks, not joined (sent and
        hashed one after another): V*3 float32, T*3 int32, then the normal and
        terminator blocks when present (`query()` says which), little-endian."""
        parts = [np.ascontiguousarray(self.vertices, dtype="<f4"),
                 np.ascontiguousarray(self.indices, dtype="<i4")]
        parts += [np.ascontiguousarray(a, dtype="<f4")
                  for a in (self.normals, self.terminator_offsets) if a is not None]
        return [memoryview(a.reshape(-1).view(np.uint8)) for a in parts]

    def body(self) -> bytes:
        """`blocks()` joined."""
        return b"".join(self.blocks())

    @cached_property
    def content_id(self) -> str:
        """The service's id of this upload: the hash of its body, made once (a scene kept
        between renders is not hashed again)."""
        return content_id(len(self.vertices), self.triangles, self.blocks())

    def query(self) -> dict[str, str]:
        """The upload's block flags (docs/api.md), only those that are on."""
        flags = {"normals": self.normals, "terminator_offsets": self.terminator_offsets}
        return {name: "true" for name, a in flags.items() if a is not None}


@dataclass(frozen=True)
class _MeshArrays:
    """One mesh in its local space: vertices (float32 read from a mesh, float64 made by
    strands.py), loop-triangle indices, and the loop triangles' corner normals (float32,
    zero on flat ones), None when no face is smooth; each loop triangle's material slot,
    None when the mesh has at most one material."""

    vertices: np.ndarray
    indices: np.ndarray
    normals: np.ndarray | None
    slots: np.ndarray | None = None


_EMPTY = _MeshArrays(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), None)


def source_key(obj: bpy.types.Object) -> int:
    """Objects sharing mesh data share this key (their geometry is read once)."""
    return obj.data.as_pointer() if obj.type == "MESH" and obj.data else obj.as_pointer()


def _source_arrays(obj: bpy.types.Object, cache: dict[int, _MeshArrays]) -> _MeshArrays:
    """The object's evaluated mesh in its own space, read once per mesh data."""
    key = source_key(obj)
    if key not in cache:
        cache[key] = _mesh_arrays(obj.data) if _is_mesh(obj) else _converted(obj)
    return cache[key]


def _is_mesh(obj: bpy.types.Object) -> bool:
    return obj.type == "MESH" and obj.data is not None


def _converted(obj: bpy.types.Object) -> _MeshArrays:
    """A mesh-like object that is not a mesh (curves, text, hair, points), made one."""
    if obj.type in _STRANDS:
        return _MeshArrays(*_STRANDS[obj.type](obj.data))
    mesh = obj.to_mesh()
    try:
        return _mesh_arrays(mesh) if mesh else _EMPTY
    finally:
        obj.to_mesh_clear()


def _smooth(mesh: bpy.types.Mesh) -> np.ndarray:
    """Each loop triangle's smooth flag (`calc_loop_triangles` done)."""
    smooth = np.empty(len(mesh.loop_triangles), dtype=bool)
    mesh.loop_triangles.foreach_get("use_smooth", smooth)
    return smooth


def _mesh_arrays(mesh: bpy.types.Mesh) -> _MeshArrays:
    """Local-space vertices, loop-triangle vertex indices and corner normals of one mesh."""
    mesh.calc_loop_triangles()
    count = len(mesh.loop_triangles)
    vertices = np.empty((len(mesh.vertices), 3), np.float32)
    indices = np.empty((count, 3), np.int32)
    normals = np.empty((count, 3, 3), np.float32) if _smooth(mesh).any() else None
    _read_mesh(mesh, vertices, indices, normals)
    slots = None
    if len(mesh.materials) > 1:
        slots = np.empty(count, np.int32)
        mesh.loop_triangles.foreach_get("material_index", slots)
    return _MeshArrays(vertices, indices, normals, slots)


def _read_mesh(mesh: bpy.types.Mesh, vertices: np.ndarray, indices: np.ndarray,
               normals: np.ndarray | None) -> None:
    """Read one mesh into arrays of its sizes (contiguous: parts of a scene's arrays too):
    vertices, loop-triangle indices and, unless None, corner normals (zero on flat
    triangles)."""
    mesh.calc_loop_triangles()
    mesh.vertices.foreach_get("co", vertices.reshape(-1))
    mesh.loop_triangles.foreach_get("vertices", indices.reshape(-1))
    if normals is not None:
        # The corner normals per triangle in one read: split_normals are corner_normals
        # by loop index (tests/addon/test_shading.py), read in a seventh of the time.
        mesh.loop_triangles.foreach_get("split_normals", normals.reshape(-1))
        normals[~_smooth(mesh)] = 0.0


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


PLACE_ROWS = 1 << 16  # rows transformed at once: float64 temporaries of 1.5 MB


@dataclass
class _Source:
    """A geometry of the flattened scene (mesh data, or an object made a mesh): its sizes,
    the instances yet to place it, and its local arrays while more than one will."""

    vertices: int
    triangles: int
    smooth: bool
    uses: int = 0
    arrays: _MeshArrays | None = None


def _sized(obj: bpy.types.Object, sources: dict[int, _Source]) -> _Source:
    """The object's source with its sizes; a mesh's data is not read yet."""
    key = source_key(obj)
    if key not in sources:
        if _is_mesh(obj):
            mesh = obj.data
            mesh.calc_loop_triangles()
            sources[key] = _Source(len(mesh.vertices), len(mesh.loop_triangles),
                                   bool(_smooth(mesh).any()))
        else:
            arrays = _converted(obj)
            sources[key] = _Source(len(arrays.vertices), len(arrays.indices),
                                   arrays.normals is not None, arrays=arrays)
    return sources[key]


def export_scene(depsgraph: bpy.types.Depsgraph) -> SceneMesh:
    """World-space triangles of every visible, renderable mesh-like object and instance,
    with their shading normals and terminator offsets (see the module docstring).

    Two passes over the depsgraph: every part's sizes, then each part read and placed
    straight into the scene's arrays (a mesh that one object uses goes from Blender into
    its place and is transformed there), so that the export holds little more than the
    upload."""
    sources: dict[int, _Source] = {}
    order: list[_Source] = []
    for inst in rendered(depsgraph):
        source = _sized(inst.object, sources)
        if source.triangles:
            source.uses += 1
            order.append(source)
    if not order:
        return SceneMesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), 0)
    triangles = sum(source.triangles for source in order)
    vertices = np.empty((sum(source.vertices for source in order), 3), np.float32)
    indices = np.empty((triangles, 3), np.int32)
    normals = (np.empty((triangles, 3, 3), np.float32)
               if any(source.smooth for source in order) else None)
    spans: dict[str, Span] = {}
    offsets: list[float] = []
    at_v = at_t = 0
    parts = iter(order)
    for inst in rendered(depsgraph):
        obj = inst.object
        source = sources[source_key(obj)]
        if not source.triangles:
            continue
        if next(parts, None) is not source:
            raise RuntimeError("The scene changed while it was read: render again")
        t = slice(at_t, at_t + source.triangles)
        mirrored = _place(obj, source, np.array(inst.matrix_world, dtype=np.float64), at_v,
                          vertices[at_v:at_v + source.vertices], indices[t],
                          None if normals is None else normals[t])
        if not inst.is_instance:
            spans[obj.original.name] = Span(at_t, source.triangles, mirrored)
        offsets.append(terminator_offset(obj))
        at_v, at_t = at_v + source.vertices, at_t + source.triangles
    return SceneMesh(vertices, indices, len(order), normals,
                     _terminators(order, offsets, normals is not None), spans)


def _place(obj: bpy.types.Object, source: _Source, matrix: np.ndarray, first_vertex: int,
           vertices: np.ndarray, indices: np.ndarray, normals: np.ndarray | None) -> bool:
    """One instance of `source` into its part of the scene's arrays, through `matrix`;
    whether the transform mirrors (then each triangle's corners are reversed, keeping
    faces outward, and its corner normals follow)."""
    arrays = source.arrays
    if arrays is None and source.uses > 1:  # read once, for this and the other instances
        arrays = source.arrays = _mesh_arrays(obj.data)
    if arrays is None:  # its only instance: read straight into place, transformed there
        local_normals = normals if source.smooth else None
        _read_mesh(obj.data, vertices, indices, local_normals)
        arrays = _MeshArrays(vertices, indices, local_normals)
    source.uses -= 1
    if not source.uses:
        source.arrays = None
    linear = matrix[:3, :3]
    mirrored = bool(np.linalg.det(linear) < 0.0)
    for a in range(0, len(vertices), PLACE_ROWS):
        rows = arrays.vertices[a:a + PLACE_ROWS].astype(np.float64)
        vertices[a:a + PLACE_ROWS] = rows @ linear.T + matrix[:3, 3]
    for a in range(0, len(indices), PLACE_ROWS):
        rows = arrays.indices[a:a + PLACE_ROWS]
        indices[a:a + PLACE_ROWS] = (rows[:, ::-1] if mirrored else rows) + first_vertex
        if normals is None:
            continue
        if arrays.normals is None:
            normals[a:a + PLACE_ROWS] = 0.0  # flat: the geometric normal
            continue
        world = _world_normals(arrays.normals[a:a + PLACE_ROWS], linear)
        normals[a:a + PLACE_ROWS] = world[:, ::-1] if mirrored else world
    return mirrored


def _terminators(order: list[_Source], offsets: list[float], smooth: bool,
                 ) -> np.ndarray | None:
    """Per-triangle terminator offsets: None without smooth faces, or when every smooth
    part has the default."""
    used = {np.float32(o) for o, source in zip(offsets, order, strict=True) if source.smooth}
    if not smooth or used == {np.float32(DEFAULT_TERMINATOR_OFFSET)}:
        return None
    return np.repeat(np.asarray(offsets, np.float32), [source.triangles for source in order])


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
    # Per instance, for the Material Index pass (not sent): its mesh's material slot per
    # triangle (None: slot 0) and the Pass Index of the material in each of its object's
    # slots (0 for an empty slot or none, as Cycles' default surface).
    materials: tuple[tuple[np.ndarray | None, np.ndarray], ...] = field(default=(),
                                                                       compare=False)

    def material_index(self, instance: np.ndarray, triangle: np.ndarray) -> np.ndarray:
        """The Material Index pass's value where each (instance, triangle in its mesh) was
        hit (instance -1: background, 0), the slot clamped to the object's slots as
        Cycles clamps it."""
        out = np.zeros(len(instance), np.float32)
        for i in np.unique(instance[instance >= 0]):
            at = instance == i
            slots, table = self.materials[i]
            slot = 0 if slots is None else np.clip(slots[triangle[at]], 0, len(table) - 1)
            out[at] = table[slot]
        return out

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


def rendered(depsgraph: bpy.types.Depsgraph,
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
               for inst in rendered(depsgraph))


def has_instances(depsgraph: bpy.types.Depsgraph) -> bool:
    """Whether the scene renders best as an instance list: some geometry is instanced
    (collection instances, instancing by vertices or faces, geometry nodes), mesh data is
    shared by several objects, or an object's ray visibility or holdout is not the
    default (only an instance list carries them). Reads no mesh."""
    view_layer = depsgraph.view_layer
    seen: set[int] = set()
    for inst in rendered(depsgraph):
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
    geometry did not change (the Rendered viewport after moving objects, F12 with
    Persistent Data: evaluated meshes stay where they were): the arrays by `source_key`,
    and each (arrays, terminator offset)'s local mesh and id. An export keeps only what
    it used."""

    arrays: dict[int, _MeshArrays] = field(default_factory=dict)
    local: dict[tuple[int, float], tuple[str, SceneMesh]] = field(default_factory=dict)

    def clear(self) -> None:
        self.keep(set())

    def forget(self, key: int) -> None:
        """Drop one source (its geometry changed)."""
        self.keep(set(self.arrays) - {key})

    def keep(self, keys: set[int]) -> None:
        """Keep only the sources of `keys`, and their local meshes (which are keyed by
        the arrays' `id()`: never kept past their arrays, whose id a new one may reuse)."""
        self.arrays = {k: a for k, a in self.arrays.items() if k in keys}
        live = {id(a) for a in self.arrays.values()}
        self.local = {k: v for k, v in self.local.items() if k[0] in live}


def _material_passes(obj: bpy.types.Object) -> np.ndarray:
    """The Pass Index of the material in each of the object's slots (at least one)."""
    return np.array([slot.material.pass_index if slot.material is not None else 0
                     for slot in obj.material_slots] or [0], np.float32)


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
    materials: list[tuple[np.ndarray | None, np.ndarray]] = []
    view_layer = depsgraph.view_layer
    used: set[int] = set()
    for inst in rendered(depsgraph):
        obj = inst.object
        used.add(source_key(obj))
        arrays = _source_arrays(obj, cache.arrays)
        if len(arrays.indices) == 0:
            continue
        key = (id(arrays), terminator_offset(obj))
        if key not in local:
            mesh = _local_mesh(arrays, key[1])
            local[key] = (mesh.content_id, mesh)
        name, mesh = local[key]
        if name not in meshes:
            position[name] = len(meshes)
            meshes[name] = mesh
        index.append(position[name])
        transforms.append(np.array(inst.matrix_world, dtype=np.float32)[:3])
        masks.append(ray_visibility(inst, view_layer))
        pass_index.append(obj.pass_index)
        materials.append((arrays.slots, _material_passes(obj)))
    cache.keep(used)  # what the scene no longer renders is let go
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
        tuple(m for m, kept in zip(materials, keep, strict=True) if kept),
    )
