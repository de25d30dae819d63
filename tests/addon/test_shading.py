"""Cycles' AO definition end to end, headless: the export's shading normals (smooth, flat,
sharp edges, custom split normals, mirrored instances) and terminator offsets, the World's
AO distance, F12 and Ctrl-F12 on a scene with flat, smooth, custom-normal and subdivided
objects, and a statistical comparison with Cycles' own AO pass that fails if the shading
normal or the terminator offset were wrong."""

from __future__ import annotations

import math
import re
from collections.abc import Iterator

import bmesh
import bpy
import numpy as np
import pytest
from blender_scenes import (
    add_camera,
    add_object,
    ao_pass,
    box_mesh,
    ctrl_f12,
    direct_film,
    f12,
    grid_mesh,
)
from cycles_reference import clean_pixels, judge, render_cycles_ao
from scenesort.backend.render.engine import count_degenerate
from scenesort.backend.wire import binary as wire

import addon
from addon import camera, client, export, prefs

WIDTH, HEIGHT = 48, 36


def uv_sphere(name: str, segments: int = 12, rings: int = 6, smooth: bool = True):
    """A low-poly UV sphere of radius 1 (facets large enough to show a terminator)."""
    mesh = bpy.data.meshes.new(name)
    bm = bmesh.new()
    bmesh.ops.create_uvsphere(bm, u_segments=segments, v_segments=rings, radius=1.0)
    for face in bm.faces:
        face.smooth = smooth
    bm.to_mesh(mesh)
    bm.free()
    return mesh


def smooth_cube_with_radial_normals(name: str) -> bpy.types.Mesh:
    """A cube shaded like a sphere: custom split normals along each corner's position."""
    mesh = box_mesh(name, size=1.2)
    mesh.shade_smooth()
    radial = [tuple(np.asarray(v.co) / np.linalg.norm(v.co)) for v in mesh.vertices]
    mesh.normals_split_custom_set_from_vertices(radial)
    return mesh


@pytest.fixture(scope="module")
def scene() -> Iterator[bpy.types.Scene]:
    """A flat floor and cube, a smooth sphere, a cube with custom normals and a smooth cube
    subdivided at render level 2 (viewport 1), seen by a camera; the engine selected."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon.register()
    scn = bpy.context.scene
    add_object(scn, "Floor", grid_mesh("Floor", 6, 8.0))
    add_object(scn, "Cube", box_mesh("Cube", size=1.0), (2.0, 1.0, 0.5))
    add_object(scn, "Sphere", uv_sphere("Sphere"), (-1.4, 0.0, 1.0))
    add_object(scn, "Custom", smooth_cube_with_radial_normals("Custom"), (0.8, -1.0, 0.6))
    subd = add_object(scn, "Subd", box_mesh("Subd", size=1.0), (-0.2, 1.8, 0.5))
    subd.data.shade_smooth()
    modifier = subd.modifiers.new("Subdivision", "SUBSURF")
    modifier.levels, modifier.render_levels = 1, 2
    add_camera(scn, (0.0, -6.5, 3.5), (math.radians(62), 0.0, 0.0), WIDTH, HEIGHT)
    scn.world = bpy.data.worlds.new("World")
    scn.world.light_settings.distance = 1.5
    scn.scenesort.spp, scn.scenesort.seed = 16, 1
    # F12 renders through the scene's filter: the one these pixel-centre comparisons with
    # Cycles use (cycles_reference.py's default film)
    scn.cycles.pixel_filter_type, scn.cycles.filter_width = "GAUSSIAN", 0.01
    scn.render.engine = "SCENESORT"
    scn.render.image_settings.file_format = "OPEN_EXR"
    scn.render.image_settings.color_depth = "32"
    prefs.preferences(bpy.context).start_on_render = True
    try:
        yield scn
    finally:
        addon.unregister()


def _triangles(name: str) -> int:
    mesh = bpy.data.objects[name].evaluated_get(bpy.context.evaluated_depsgraph_get()).data
    mesh.calc_loop_triangles()
    return len(mesh.loop_triangles)


def _rows(name: str) -> slice:
    """Where object `name`'s triangles are in the viewport export (the depsgraph's order)."""
    depsgraph = bpy.context.evaluated_depsgraph_get()
    start = 0
    for inst in depsgraph.object_instances:
        if inst.object.type != "MESH":
            continue
        count = _triangles(inst.object.name)
        if inst.object.name == name:
            return slice(start, start + count)
        start += count
    raise KeyError(name)


MESHES = ("Floor", "Cube", "Sphere", "Custom", "Subd")


def test_export_sends_corner_normals_of_smooth_faces_only(scene) -> None:
    mesh = export.export_scene(bpy.context.evaluated_depsgraph_get())
    assert mesh.normals is not None and mesh.normals.shape == (mesh.triangles, 3, 3)
    assert mesh.terminator_offsets is None  # every object has Blender's default 0.1
    assert mesh.query() == {"normals": "true"}
    for flat in ("Floor", "Cube"):  # flat faces: zero corners (the geometric normal)
        assert np.all(mesh.normals[_rows(flat)] == 0.0)
    sphere = bpy.data.objects["Sphere"].data
    loops = np.array([t.loops for t in sphere.loop_triangles])
    corner = np.array([n.vector for n in sphere.corner_normals])[loops]
    np.testing.assert_allclose(mesh.normals[_rows("Sphere")], corner, atol=1e-6)
    # Custom split normals: each corner points along its vertex (stored compressed).
    custom = bpy.data.objects["Custom"].data
    tris = np.array([t.vertices for t in custom.loop_triangles])
    radial = np.array([v.co for v in custom.vertices])[tris]
    radial /= np.linalg.norm(radial, axis=2, keepdims=True)
    np.testing.assert_allclose(mesh.normals[_rows("Custom")], radial, atol=2e-3)
    body = mesh.body()
    v, t = len(mesh.vertices), mesh.triangles
    assert len(body) == 12 * v + 48 * t
    decoded = wire.decode_scene(body, v, t, normals=True,
                                count_degenerate=count_degenerate)  # the service reads it back
    np.testing.assert_array_equal(decoded.normals, mesh.normals)
    assert client.scene_id(v, t, body) == decoded.scene_id


def test_sharp_edges_and_flat_scenes(scene) -> None:
    """Sharp edges split the corner normals (a smooth cube with sharp edges shades as its
    faces); a scene of flat faces only sends no normal block: today's upload, byte for
    byte."""
    mesh = box_mesh("Sharp", size=1.0)
    mesh.shade_smooth()
    for edge in mesh.edges:
        edge.use_edge_sharp = True
    obj = add_object(scene, "Sharp", mesh, (0.0, 3.0, 0.5))
    hidden = [o for o in scene.objects if o.type == "MESH" and o.name not in ("Floor", "Cube")]
    for o in hidden:
        o.hide_viewport = True
    try:
        flat = export.export_scene(bpy.context.evaluated_depsgraph_get())
        obj.hide_viewport = False
        sharp = export.export_scene(bpy.context.evaluated_depsgraph_get())
        rows = _rows("Sharp")
    finally:
        for o in hidden:
            o.hide_viewport = False
        bpy.data.objects.remove(obj)
    assert flat.normals is None and flat.query() == {}
    plain = flat.vertices.astype("<f4").tobytes() + flat.indices.astype("<i4").tobytes()
    assert flat.body() == plain
    v = sharp.vertices.astype(np.float64)[sharp.indices[rows]]
    faces = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    faces /= np.linalg.norm(faces, axis=1, keepdims=True)
    np.testing.assert_allclose(sharp.normals[rows], np.repeat(faces[:, None], 3, axis=1),
                               atol=1e-6)


def test_mirrored_instances_keep_normals_outward_and_offsets_travel(scene) -> None:
    sphere = bpy.data.objects["Sphere"]
    sphere.scale = (-1.0, 1.0, 2.0)  # mirrored and stretched
    sphere.shadow_terminator_geometry_offset = 0.3
    try:
        mesh = export.export_scene(bpy.context.evaluated_depsgraph_get())
    finally:
        sphere.scale = (1.0, 1.0, 1.0)
        sphere.shadow_terminator_geometry_offset = 0.1
    rows = _rows("Sphere")
    n = mesh.normals[rows]
    p = mesh.vertices[mesh.indices[rows]] - np.float32(sphere.location)
    np.testing.assert_allclose(np.linalg.norm(n, axis=2), 1.0, atol=1e-5)
    # The normal of the ellipsoid x^2 + y^2 + (z/2)^2 = 1 at p is along (x, y, z/4).
    along = p * np.float32([1, 1, 0.25])
    along /= np.linalg.norm(along, axis=2, keepdims=True)
    assert np.all(np.einsum("tck,tck->tc", n, along) > 0.9)  # outward, inverse transpose
    v = mesh.vertices.astype(np.float64)[mesh.indices[rows]]
    winding = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    assert np.all(np.einsum("tk,tk->t", winding, n.mean(axis=1)) > 0)  # agrees with faces
    assert mesh.query() == {"normals": "true", "terminator_offsets": "true"}
    offsets = mesh.terminator_offsets
    assert np.all(offsets[rows] == np.float32(0.3))
    assert np.all(np.delete(offsets, np.arange(rows.start, rows.stop)) == np.float32(0.1))


def _direct(scn: bpy.types.Scene, distance: float, **kwargs) -> tuple[np.ndarray, np.ndarray]:
    """AO and coverage from the engine itself on the exported scene (`direct_film`;
    subdivision at its render level, as F12 exports it), without the add-on or the
    service."""
    modifier = bpy.data.objects["Subd"].modifiers["Subdivision"]
    levels, modifier.levels = modifier.levels, modifier.render_levels
    try:
        depsgraph = bpy.context.evaluated_depsgraph_get()
        mesh = export.export_scene(depsgraph)
        cam = camera.camera_dict(scn, depsgraph)
    finally:
        modifier.levels = levels
    return direct_film(scn, mesh, cam, distance=distance, **kwargs)


def test_f12_shades_with_the_exported_normals_and_the_worlds_distance(scene, tmp_path) -> None:
    """F12 equals a direct engine call with the exported normals at the World's AO
    distance; without a World it is 10; the panel's AO distance overrides both. The smooth
    and custom-normal objects differ from a flat render of the same scene."""
    props = scene.scenesort
    world = scene.world
    rgba = f12(scene, tmp_path / "world")
    ao, coverage = _direct(scene, 1.5)
    np.testing.assert_array_equal(rgba[..., 0], ao_pass(ao, coverage))
    flat, _ = _direct(scene, 1.5, normals=None)
    assert np.mean(np.abs(flat - ao)[coverage > 0]) > 0.01  # the normals matter
    scene.world = None
    try:
        rgba = f12(scene, tmp_path / "no_world")
    finally:
        scene.world = world
    ao, coverage = _direct(scene, 10.0)
    np.testing.assert_array_equal(rgba[..., 0], ao_pass(ao, coverage))
    props.ao_distance = 0.5
    try:
        rgba = f12(scene, tmp_path / "override")
    finally:
        props.ao_distance = 0.0
    ao, coverage = _direct(scene, 0.5)
    np.testing.assert_array_equal(rgba[..., 0], ao_pass(ao, coverage))


def test_ctrl_f12_renders_three_frames_of_the_moving_smooth_sphere(scene, tmp_path) -> None:
    """Three frames through Blender's output, the subdivided cube at its render level."""
    sphere = bpy.data.objects["Sphere"]
    sphere.rotation_euler = (0.0, 0.0, 0.0)
    sphere.keyframe_insert("rotation_euler", frame=1)
    sphere.rotation_euler = (0.0, math.radians(40), math.radians(90))
    sphere.keyframe_insert("rotation_euler", frame=3)
    try:
        images = ctrl_f12(scene, tmp_path)
    finally:
        sphere.animation_data_clear()
        sphere.rotation_euler = (0.0, 0.0, 0.0)
        scene.frame_set(1)
    frames = [np.asarray(img, np.float32) for img in images]
    assert not np.array_equal(frames[0], frames[1]) and not np.array_equal(frames[1], frames[2])
    render_subd = 6 * 16 * 2  # a cube at level 2: 16 quads per face
    expected = sum(_triangles(n) for n in MESHES if n != "Subd") + render_subd
    assert _triangles("Subd") == 6 * 4 * 2  # the viewport shows level 1
    note = images[1].text["scenesort"]
    assert re.match(rf"{expected:,} triangles \|", note), note


SPP = 512


def test_matches_cycles_ao_pass_statistically(scene, tmp_path) -> None:
    """Against Cycles' AO pass at the same pixel centres and samples (the World's
    distance, default terminator offset 0.1): on the clean hit pixels of the smooth
    sphere and the flat floor, scenesort's RMSE to one Cycles render is within 1.25x
    Cycles' RMSE between two seeds, and its mean is unbiased (4 standard errors). The same
    render with flat shading or without the terminator offset fails the same test, so the
    test would catch either."""
    props = scene.scenesort
    props.spp = SPP
    try:
        ours = f12(scene, tmp_path / "ours")[..., 0]
        cycles_a, alpha, _ = render_cycles_ao(scene, tmp_path / "cycles_a", SPP, seed=11)
        cycles_b, _, _ = render_cycles_ao(scene, tmp_path / "cycles_b", SPP, seed=12)
        _, coverage = _direct(scene, 1.5)
        geometric, _ = _direct(scene, 1.5, normals=None)
        no_offset, _ = _direct(scene, 1.5, terminator_offset=0.0)
    finally:
        props.spp = 16
    hit = coverage > 0
    sky = clean_pixels(~hit)  # (a silhouette within a pixel's filter may give 1/512)
    assert sky.sum() > 50 and np.all(alpha[sky] == 0.0) and np.all(cycles_a[sky] == 0.0)
    assert np.all(ours[~hit] == 0.0)  # background 0 in both
    clean = clean_pixels((alpha == 1.0) & hit)
    assert clean.sum() > 300

    cycles_rmse = float(np.sqrt(np.mean((cycles_b - cycles_a)[clean] ** 2)))
    rmse, z = judge(ours, cycles_a, clean)
    assert rmse <= 1.25 * cycles_rmse, (rmse, cycles_rmse)
    assert z < 4.0, z
    # Measured: scenesort 0.0048 against Cycles' own 0.0051 (z 0.8); flat shading 0.054,
    # no terminator offset 0.045.
    for wrong in (geometric, no_offset):
        rmse, z = judge(wrong, cycles_a, clean)
        assert rmse > 1.25 * cycles_rmse or z > 4.0, (rmse, cycles_rmse, z)
