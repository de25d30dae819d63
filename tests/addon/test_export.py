"""Scene export: modifiers applied, instances included, hidden and unrenderable objects out."""

from __future__ import annotations

import bpy
import numpy as np
import pytest
from blender_scenes import add_object, box_mesh

from addon import client, export


def _depsgraph() -> bpy.types.Depsgraph:
    return bpy.context.evaluated_depsgraph_get()


def _evaluated_triangles(obj: bpy.types.Object) -> int:
    """Loop triangles of an object's evaluated mesh, counted by Blender itself."""
    mesh = obj.evaluated_get(_depsgraph()).data
    mesh.calc_loop_triangles()
    return len(mesh.loop_triangles)


@pytest.fixture
def mixed_scene(registered: bpy.types.Scene) -> dict[str, bpy.types.Object]:
    """A subdivided cube, a collection instanced twice, a hidden and an unrenderable cube."""
    scene = registered
    modified = add_object(scene, "Modified", box_mesh("ModifiedMesh"), (0.0, 0.0, 0.0))
    mod = modified.modifiers.new("Subsurf", "SUBSURF")
    mod.levels = 2  # 6 quads -> 96 quads -> 192 triangles

    parts = bpy.data.collections.new("Parts")
    scene.collection.children.link(parts)
    part = bpy.data.objects.new("Part", box_mesh("PartMesh", size=1.0))
    parts.objects.link(part)
    ghost = bpy.data.objects.new("PartNotRendered", box_mesh("GhostMesh", size=1.0))
    ghost.hide_render = True  # skipped in the instances too, as Cycles does
    parts.objects.link(ghost)
    # The source collection is excluded from the view layer, as usual for assets.
    scene.view_layers[0].layer_collection.children["Parts"].exclude = True
    instancers = []
    for i, x in enumerate((10.0, -10.0)):
        empty = add_object(scene, f"Instancer{i}", None, (x, 0.0, 0.0))
        empty.instance_type = "COLLECTION"
        empty.instance_collection = parts
        instancers.append(empty)
    instancers[1].scale = (-1.0, 1.0, 1.0)  # a mirrored instance

    hidden = add_object(scene, "Hidden", box_mesh("HiddenMesh"), (0.0, 20.0, 0.0))
    hidden.hide_set(True)
    unrendered = add_object(scene, "NoRender", box_mesh("NoRenderMesh"), (0.0, -20.0, 0.0))
    unrendered.hide_render = True
    off = bpy.data.collections.new("RenderOff")
    off.hide_render = True
    scene.collection.children.link(off)
    off.objects.link(bpy.data.objects.new("InRenderOff", box_mesh("OffMesh")))
    return {"modified": modified, "part": part, "hidden": hidden, "unrendered": unrendered}


def test_counts_match_evaluated_depsgraph_for_visible_objects(mixed_scene) -> None:
    modified, part = mixed_scene["modified"], mixed_scene["part"]
    expected = _evaluated_triangles(modified) + 2 * _evaluated_triangles(part)
    assert _evaluated_triangles(modified) == 192  # the modifier was applied
    mesh = export.export_scene(_depsgraph())
    assert mesh.triangles == expected == 192 + 24
    assert mesh.objects == 3
    assert mesh.vertices.dtype == np.float32 and mesh.indices.dtype == np.int32
    assert mesh.vertices.shape[1] == 3 and mesh.indices.shape[1] == 3
    assert mesh.indices.min() >= 0 and mesh.indices.max() < len(mesh.vertices)


def test_vertices_are_world_space_and_skip_hidden(mixed_scene) -> None:
    mesh = export.export_scene(_depsgraph())
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    # Instances of the unit cube at x = +-10 bound the scene in x, the subdivided cube
    # (its evaluated vertices, read one by one) in y and z; the hidden cube (y = 20)
    # and the unrenderable ones (y = -20, origin) would widen it.
    evaluated = mixed_scene["modified"].evaluated_get(_depsgraph()).data
    box = np.array([tuple(v.co) for v in evaluated.vertices])
    assert box[:, 1].max() < 0.9  # subdivision rounded the cube
    np.testing.assert_allclose(lo, [-10.5, *box.min(axis=0)[1:]], atol=1e-6)
    np.testing.assert_allclose(hi, [10.5, *box.max(axis=0)[1:]], atol=1e-6)


def test_mirrored_instance_keeps_faces_outward(mixed_scene) -> None:
    """A negative scale flips winding; the export flips it back so normals point out."""
    mesh = export.export_scene(_depsgraph())
    tris = mesh.vertices[mesh.indices].astype(np.float64)
    centroids = tris.mean(axis=1)
    normals = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    for centre in (10.0, -10.0):
        sel = np.abs(centroids[:, 0] - centre) < 1.0
        assert sel.sum() == 12
        outward = np.einsum("ij,ij->i", normals[sel], centroids[sel] - [centre, 0.0, 0.0])
        assert np.all(outward > 0), centre


def test_export_leaves_the_scene_alone(mixed_scene) -> None:
    bpy.context.view_layer.update()  # matrix_world is derived: let Blender settle it first
    before = {
        o.name: (tuple(map(tuple, o.matrix_world)), len(o.modifiers)) for o in bpy.data.objects
    }
    meshes = len(bpy.data.meshes)
    export.export_scene(_depsgraph())
    after = {
        o.name: (tuple(map(tuple, o.matrix_world)), len(o.modifiers)) for o in bpy.data.objects
    }
    assert before == after and len(bpy.data.meshes) == meshes


def test_body_layout_and_scene_id_match_the_service(mixed_scene) -> None:
    """The upload body is V*3 float32 then T*3 int32, and the add-on's id is the service's."""
    from scenesort.backend.render.engine import count_degenerate
    from scenesort.backend.wire import binary as wire

    mesh = export.export_scene(_depsgraph())
    body = mesh.body()
    v, t = len(mesh.vertices), mesh.triangles
    assert len(body) == 12 * v + 12 * t
    decoded = wire.decode_scene(body, v, t, count_degenerate=count_degenerate)
    np.testing.assert_array_equal(decoded.vertices, mesh.vertices)
    np.testing.assert_array_equal(decoded.indices, mesh.indices)
    assert client.scene_id(v, t, body) == decoded.scene_id == wire.scene_hash(v, t, body)


def test_unchanged_scene_has_the_same_id_and_a_change_a_new_one(mixed_scene) -> None:
    first = export.export_scene(_depsgraph())
    again = export.export_scene(_depsgraph())
    ids = [client.scene_id(len(m.vertices), m.triangles, m.body()) for m in (first, again)]
    assert ids[0] == ids[1]
    mixed_scene["modified"].location.z += 0.5
    moved = export.export_scene(_depsgraph())
    assert client.scene_id(len(moved.vertices), moved.triangles, moved.body()) != ids[0]


def test_empty_scene_exports_nothing(registered: bpy.types.Scene) -> None:
    mesh = export.export_scene(_depsgraph())
    assert mesh.triangles == 0 and mesh.vertices.shape == (0, 3)
