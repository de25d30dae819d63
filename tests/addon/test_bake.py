"""Blender's Bake (Ambient Occlusion) with the scenesort engine, headless with a real
service: the texels' points are Cycles' own (a position bake), image textures and colour
attributes match Cycles' AO bake statistically, several objects in one bake, a mirrored
object, Blender's own messages for what it refuses, other passes refused by name, Esc."""

from __future__ import annotations

import math
import re
from collections.abc import Iterator
from typing import ClassVar

import bpy
import numpy as np
import pytest
from blender_scenes import add_object, bake_target, grid_mesh, uv_sphere_mesh
from cycles_reference import clean_pixels, judge

import addon
from addon import bake, engine, export, service

SIZE = 64  # image texels per side
SPP = 256


class Where(engine.AoEngine, bpy.types.RenderEngine):
    """Bakes each texel's world position, as the engine finds its point (bake.py), so that
    Cycles' Position bake can judge the mapping."""

    bl_idname = "SCENESORT_WHERE"
    bl_label = "scenesort AO (positions)"
    bl_use_preview = False

    def bake(self, depsgraph, obj, pass_type, pass_filter, width, height) -> None:  # noqa: ANN001
        mesh = export.export_scene(depsgraph)
        result = self.begin_result(0, 0, width, height, layer=self._bake_layer(), view="")
        primitive = np.empty(width * height * 3, np.float32)
        result.layers[0].passes["BakePrimitive"].rect.foreach_get(primitive)
        texels, tri, u, v = bake.texel_points(primitive.reshape(-1, 3),
                                              mesh.spans[obj.original.name])  # fmt: skip
        corners = mesh.vertices[mesh.indices[tri]].astype(np.float64)
        w = np.stack([1.0 - u - v, u, v], 1)[:, :, None]
        rgba = np.zeros((width * height, 4), np.float32)
        rgba[texels, :3] = (w * corners).sum(axis=1)
        rgba[texels, 3] = 1.0
        self.fill(result, {"Combined": rgba})
        self.end_result(result)


class Stopper(engine.AoEngine, bpy.types.RenderEngine):
    """The engine, with Esc pressed once its bake job runs."""

    bl_idname = "SCENESORT_STOPPER"
    bl_label = "scenesort AO (Esc)"
    bl_use_preview = False
    said: ClassVar[list[str]] = []

    def stopped(self) -> bool:
        return self.task is not None and any(s.startswith("running: ao")
                                             for s in self.task.steps)  # fmt: skip

    def show(self, text: str) -> None:
        Stopper.said.append(text)
        super().show(text)


def _uv_sphere(name: str, scene: bpy.types.Scene, location, mirrored: bool = False):
    obj = add_object(scene, name, uv_sphere_mesh(name, 16, 8, smooth=True), location)
    obj.modifiers.new("Subdivision", "SUBSURF").levels = 1  # render level 2: 16x the faces
    if mirrored:
        obj.scale.x = -1.0
    return obj


def _image_target(obj: bpy.types.Object, size: int = SIZE,
                  image: bpy.types.Image | None = None) -> bpy.types.Image:
    return bake_target(obj, size, image)


def _pixels(image: bpy.types.Image) -> np.ndarray:
    out = np.empty(len(image.pixels), np.float32)
    image.pixels.foreach_get(out)
    return out.reshape(-1, 4)


def _select(scene: bpy.types.Scene, *objects: bpy.types.Object) -> None:
    for obj in scene.objects:
        obj.select_set(obj in objects)
    bpy.context.view_layer.objects.active = objects[0]


def _bake(scene, engine_name: str, objects, kind: str = "AO", **options) -> dict[str, np.ndarray]:
    """Bake `objects` (fresh -1 targets) with `engine_name`: each object's texels."""
    images = {obj.name: _image_target(obj) for obj in objects}
    _select(scene, *objects)
    scene.render.engine = engine_name
    assert bpy.ops.object.bake(type=kind, use_clear=False, margin=0, **options) == {"FINISHED"}
    return {name: _pixels(image) for name, image in images.items()}


@pytest.fixture(scope="module")
def scene() -> Iterator[bpy.types.Scene]:
    """A floor (8x8 quads, unwrapped to the whole texture) under a smooth, subdivided
    sphere resting on it and a mirrored one beside it; AO distance 1.5 from the World."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon.register()
    for cls in (Where, Stopper):
        bpy.utils.register_class(cls)
    scene = bpy.context.scene
    floor_mesh = grid_mesh("Floor", 8, 8.0)
    floor_mesh.uv_layers.new(name="UVMap")
    loops = np.empty(len(floor_mesh.loops), np.int32)
    floor_mesh.loops.foreach_get("vertex_index", loops)
    co = np.empty(len(floor_mesh.vertices) * 3, np.float32)
    floor_mesh.vertices.foreach_get("co", co)
    uv = (co.reshape(-1, 3)[loops, :2] + 4.0) / 8.0
    floor_mesh.uv_layers["UVMap"].data.foreach_set("uv", uv.ravel())
    add_object(scene, "Floor", floor_mesh)
    _uv_sphere("Ball", scene, (0.0, 0.0, 1.0))
    _uv_sphere("Mirrored", scene, (2.6, 0.0, 1.0), mirrored=True)
    scene.world = bpy.data.worlds.new("World")
    scene.world.light_settings.distance = 1.5
    scene.scenesort.ao_distance, scene.scenesort.spp = 0.0, SPP  # 0: the World's distance
    scene.cycles.device, scene.cycles.samples = "CPU", SPP
    scene.cycles.use_adaptive_sampling, scene.cycles.use_denoising = False, False
    try:
        yield scene
    finally:
        proc = service._process
        for cls in (Stopper, Where):
            bpy.utils.unregister_class(cls)
        addon.unregister()
        assert proc is None or proc.poll() is not None


def test_the_texels_points_are_cycles_own(scene) -> None:
    """Each texel's point, as the engine finds it from Blender's bake pass, is the world
    position Cycles bakes there (its Position pass at 1 sample: the texel centre), for the
    floor, a smooth subdivided sphere and a mirrored one, in one bake."""
    objects = [scene.objects[n] for n in ("Floor", "Ball", "Mirrored")]
    scene.cycles.samples = 1
    try:
        cycles = _bake(scene, "CYCLES", objects, "POSITION")
    finally:
        scene.cycles.samples = SPP
    ours = _bake(scene, Where.bl_idname, objects)
    for name in cycles:
        covered = cycles[name][:, 3] > 0.0
        assert covered.sum() > 1000, name
        np.testing.assert_array_equal(ours[name][:, 3] > 0.0, covered)  # the same texels
        np.testing.assert_allclose(ours[name][covered, :3], cycles[name][covered, :3],
                                   atol=2e-5, err_msg=name)  # fmt: skip


def _interior(covered: np.ndarray) -> np.ndarray:
    """Texels whose 3x3 neighbourhood is covered: away from the UV islands' borders."""
    return clean_pixels(covered.reshape(SIZE, SIZE)).ravel()


def test_image_bakes_match_cycles_ao_bake(scene) -> None:
    """On interior texels of the floor and both spheres, scenesort's RMSE to one Cycles AO
    bake is within 1.25x Cycles' own between two seeds, with no bias (4 standard errors);
    the sphere's underside, against the floor, is dark."""
    objects = [scene.objects[n] for n in ("Floor", "Ball", "Mirrored")]
    scene.cycles.seed = 11
    cycles_a = _bake(scene, "CYCLES", objects)
    scene.cycles.seed = 12
    cycles_b = _bake(scene, "CYCLES", objects)
    ours = _bake(scene, "SCENESORT", objects)
    for name in cycles_a:
        covered = cycles_a[name][:, 3] >= 0.0
        np.testing.assert_array_equal(ours[name][:, 3] >= 0.0, covered)
        inner = _interior(covered)
        assert inner.sum() > 500, name
        cycles_rmse, _ = judge(cycles_b[name][:, 0], cycles_a[name][:, 0], inner)
        rmse, z = judge(ours[name][:, 0], cycles_a[name][:, 0], inner)
        assert rmse <= 1.25 * cycles_rmse and z < 4.0, (name, rmse, cycles_rmse, z)
    ball = ours["Ball"][:, 0][ours["Ball"][:, 3] >= 0.0]
    assert ball.min() < 0.2 and ball.max() > 0.9


def test_colour_attribute_bakes_match_cycles(scene) -> None:
    """A colour-attribute bake (one texel per face corner) of the sphere against Cycles'
    own, the same statistics per corner."""
    ball = scene.objects["Ball"]
    attribute = ball.data.color_attributes.new("AO", "FLOAT_COLOR", "CORNER")
    ball.data.color_attributes.active_color = attribute
    _select(scene, ball)
    values = {}
    try:
        for engine_name, seed in (("CYCLES", 11), ("CYCLES", 12), ("SCENESORT", 0)):
            scene.render.engine, scene.cycles.seed = engine_name, seed
            assert bpy.ops.object.bake(type="AO", target="VERTEX_COLORS") == {"FINISHED"}
            colours = np.empty(len(ball.data.loops) * 4, np.float32)
            ball.data.color_attributes["AO"].data.foreach_get("color", colours)
            values[engine_name, seed] = colours.reshape(-1, 4)[:, 0]
    finally:
        ball.data.color_attributes.remove(ball.data.color_attributes["AO"])
    every = np.ones(len(ball.data.loops), bool)
    cycles_rmse, _ = judge(values["CYCLES", 12], values["CYCLES", 11], every)
    rmse, z = judge(values["SCENESORT", 0], values["CYCLES", 11], every)
    assert rmse <= 1.25 * cycles_rmse and z < 4.0, (rmse, cycles_rmse, z)


def test_selected_to_active_bakes_the_high_poly_onto_the_low_poly(scene) -> None:
    """A coarse flat-shaded sphere (the active object) takes the AO of the smooth,
    subdivided ball inside its cage (Selected to Active, extrusion 0.2): Blender maps the
    texels to the high-poly surface and hides the low-poly from the bake; the result
    matches Cycles' own such bake."""
    low = add_object(scene, "Low", uv_sphere_mesh("Low", 8, 4, smooth=False), (0.0, 0.0, 1.0))
    ball = scene.objects["Ball"]
    options = dict(use_selected_to_active=True, cage_extrusion=0.2)
    try:
        runs = {}
        for engine_name, seed in (("CYCLES", 11), ("CYCLES", 12), ("SCENESORT", 0)):
            image = _image_target(low)
            _select(scene, low, ball)
            scene.render.engine, scene.cycles.seed = engine_name, seed
            assert bpy.ops.object.bake(type="AO", use_clear=False, margin=0,
                                       **options) == {"FINISHED"}  # fmt: skip
            runs[engine_name, seed] = _pixels(image)
    finally:
        bpy.data.objects.remove(low)
    covered = runs["CYCLES", 11][:, 3] >= 0.0
    np.testing.assert_array_equal(runs["SCENESORT", 0][:, 3] >= 0.0, covered)
    inner = _interior(covered)
    assert inner.sum() > 500
    cycles_rmse, _ = judge(runs["CYCLES", 12][:, 0], runs["CYCLES", 11][:, 0], inner)
    rmse, z = judge(runs["SCENESORT", 0][:, 0], runs["CYCLES", 11][:, 0], inner)
    assert rmse <= 1.25 * cycles_rmse and z < 4.0, (rmse, cycles_rmse, z)


def test_a_second_bake_of_the_unchanged_scene_sends_only_the_texels(scene) -> None:
    """The service's cache serves the scene and its BVH: the second bake asks for the
    scene by its hash (HEAD), uploads nothing and builds nothing new."""
    ball = scene.objects["Ball"]
    scene.render.engine = "SCENESORT"
    scene.scenesort.spp = 8
    log = service.log_path()
    try:
        for _ in range(2):
            _image_target(ball)
            _select(scene, ball)
            before = len(log.read_text())
            assert bpy.ops.object.bake(type="AO") == {"FINISHED"}
            requests = log.read_text()[before:]
    finally:
        scene.scenesort.spp = SPP
    assert re.search(r"HEAD /v1/scenes/[0-9a-f]+ -> 200", requests), requests
    assert not re.search(r"POST /v1/scenes\?", requests), requests  # no upload
    assert re.search(r"POST /v1/scenes/[0-9a-f]+/surface-jobs\?points=\d+", requests)


def _udim_tiles(image: bpy.types.Image, folder) -> dict[int, np.ndarray]:  # noqa: ANN001
    """Each tile of a tiled image, saved as EXR and read back: (texels, 4) per number."""
    image.filepath_raw = str(folder / "tile.<UDIM>.exr")
    image.file_format = "OPEN_EXR"
    image.save()
    tiles = {}
    for tile in image.tiles:
        loaded = bpy.data.images.load(str(folder / f"tile.{tile.number}.exr"))
        tiles[tile.number] = _pixels(loaded)
        bpy.data.images.remove(loaded)
    return tiles


def test_a_udim_image_is_baked_tile_by_tile(scene, tmp_path) -> None:
    """A floor whose right half lies in UDIM tile 1002: each tile's texels get the points
    of Cycles' Position bake, and AO."""
    floor = scene.objects["Floor"]
    layer = floor.data.uv_layers["UVMap"].data
    uv = np.empty(len(layer) * 2, np.float32)
    layer.foreach_get("uv", uv)
    moved = uv.reshape(-1, 2).copy()
    right = np.repeat(moved.reshape(-1, 4, 2)[:, :, 0].mean(axis=1) > 0.5, 4)  # per quad
    moved[right, 0] += 1.0
    layer.foreach_set("uv", moved.ravel())
    try:
        baked = {}
        for engine_name, kind in (("CYCLES", "POSITION"), (Where.bl_idname, "AO"),
                                  ("SCENESORT", "AO")):  # fmt: skip
            image = bpy.data.images.new(f"udim {engine_name}", SIZE, SIZE, float_buffer=True,
                                        tiled=True)  # fmt: skip
            image.tiles.new(tile_number=1002)
            for tile in image.tiles:
                image.tiles.active = tile
                with bpy.context.temp_override(edit_image=image):
                    bpy.ops.image.tile_fill(color=(-1, -1, -1, -1), width=SIZE, height=SIZE,
                                            float=True)  # fmt: skip
            _image_target(floor, image=image)
            _select(scene, floor)
            scene.render.engine, scene.cycles.samples = engine_name, 1
            assert bpy.ops.object.bake(type=kind, use_clear=False, margin=0) == {"FINISHED"}
            folder = tmp_path / engine_name
            folder.mkdir()
            baked[engine_name] = _udim_tiles(image, folder)
    finally:
        layer.foreach_set("uv", uv)
        scene.cycles.samples = SPP
    for number in (1001, 1002):
        cycles, where = baked["CYCLES"][number], baked[Where.bl_idname][number]
        covered = cycles[:, 3] > 0.0
        assert covered.sum() > 1000, number
        np.testing.assert_array_equal(where[:, 3] > 0.0, covered)
        np.testing.assert_allclose(where[covered, :3], cycles[covered, :3], atol=2e-5)
        ao = baked["SCENESORT"][number]
        assert np.all((ao[covered, 0] >= 0.0) & (ao[covered, 0] <= 1.0)), number


def test_cycles_bake_panels_show_for_the_engine(scene) -> None:
    """Render Properties > Bake (type, Selected to Active, output, margin) is Cycles'
    own panel, shown for this engine too; given back at unregister (test_engine)."""
    scene.render.engine = "SCENESORT"
    for name in engine.BAKE_PANELS:
        panel = getattr(bpy.types, name)
        assert "SCENESORT" in panel.COMPAT_ENGINES and panel.poll(bpy.context), name
    assert "SCENESORT" not in bpy.types.CYCLES_RENDER_PT_bake_influence.COMPAT_ENGINES


@pytest.mark.parametrize("space", ["TANGENT", "OBJECT"])
def test_normal_bakes_are_cycles_own(scene, space: str) -> None:
    """A Normal bake in tangent and in object space (with a swizzle) is Cycles' texel for
    texel on the floor, the smooth subdivided sphere and the mirrored one: the engine
    hands Blender world-space normals and Blender converts them for both engines."""
    objects = [scene.objects[n] for n in ("Floor", "Ball", "Mirrored")]
    options = {"normal_space": space, "normal_r": "NEG_Y", "normal_g": "POS_X"}
    scene.cycles.samples = 1
    try:
        cycles = _bake(scene, "CYCLES", objects, "NORMAL", **options)
    finally:
        scene.cycles.samples = SPP
    ours = _bake(scene, "SCENESORT", objects, "NORMAL", **options)
    for name in cycles:
        covered = cycles[name][:, 3] >= 0.0
        assert covered.sum() > 1000, name
        np.testing.assert_array_equal(ours[name][:, 3] >= 0.0, covered)
        np.testing.assert_allclose(ours[name][covered, :3], cycles[name][covered, :3],
                                   atol=1e-3, err_msg=name)  # fmt: skip


def test_a_colour_attribute_normal_bake_is_cycles_own(scene) -> None:
    """One normal per face corner of the subdivided smooth sphere, in object space (in
    its own tangent space every corner is (0.5, 0.5, 1), which would check nothing), as
    Cycles bakes them."""
    ball = scene.objects["Ball"]
    attribute = ball.data.color_attributes.new("N", "FLOAT_COLOR", "CORNER")
    ball.data.color_attributes.active_color = attribute
    _select(scene, ball)
    scene.cycles.samples = 1
    values = {}
    try:
        for engine_name in ("CYCLES", "SCENESORT"):
            scene.render.engine = engine_name
            assert bpy.ops.object.bake(type="NORMAL", target="VERTEX_COLORS",
                                       normal_space="OBJECT") == {"FINISHED"}  # fmt: skip
            colours = np.empty(len(ball.data.loops) * 4, np.float32)
            ball.data.color_attributes["N"].data.foreach_get("color", colours)
            values[engine_name] = colours.reshape(-1, 4)[:, :3]
    finally:
        scene.cycles.samples = SPP
        ball.data.color_attributes.remove(ball.data.color_attributes["N"])
    assert np.ptp(values["CYCLES"], axis=0).min() > 0.5  # normals all round, not one
    np.testing.assert_allclose(values["SCENESORT"], values["CYCLES"], atol=1e-3)


def test_selected_to_active_normal_bake_is_cycles_own(scene) -> None:
    """High to low poly, the usual normal bake: a coarse flat-shaded sphere takes the
    smooth ball's normals in its own tangent space, as Cycles bakes them."""
    low = add_object(scene, "Low", uv_sphere_mesh("Low", 8, 4, smooth=False), (0.0, 0.0, 1.0))
    ball = scene.objects["Ball"]
    scene.cycles.samples = 1
    try:
        runs = {}
        for engine_name in ("CYCLES", "SCENESORT"):
            image = _image_target(low)
            _select(scene, low, ball)
            scene.render.engine = engine_name
            assert bpy.ops.object.bake(type="NORMAL", use_clear=False, margin=0,
                                       use_selected_to_active=True,
                                       cage_extrusion=0.2) == {"FINISHED"}  # fmt: skip
            runs[engine_name] = _pixels(image)
    finally:
        scene.cycles.samples = SPP
        bpy.data.objects.remove(low)
    covered = runs["CYCLES"][:, 3] >= 0.0
    assert covered.sum() > 1000
    np.testing.assert_array_equal(runs["SCENESORT"][:, 3] >= 0.0, covered)
    np.testing.assert_allclose(runs["SCENESORT"][covered, :3], runs["CYCLES"][covered, :3],
                               atol=1e-3)  # fmt: skip


def test_a_normal_bake_warns_of_bump_nodes_it_ignores(scene) -> None:
    """Cycles' Normal bake applies a material's Bump node (here it moves the texels'
    normals by far more than 1e-3); this one does not, and says so."""
    ball = scene.objects["Ball"]
    image = _image_target(ball)
    tree = ball.data.materials[0].node_tree
    bump, noise = tree.nodes.new("ShaderNodeBump"), tree.nodes.new("ShaderNodeTexNoise")
    noise.inputs["Scale"].default_value = 40.0
    bump.inputs["Distance"].default_value = 1.0
    tree.links.new(noise.outputs["Fac"], bump.inputs["Height"])
    tree.links.new(bump.outputs["Normal"], tree.nodes["Principled BSDF"].inputs["Normal"])
    _select(scene, ball)
    scene.render.engine, scene.cycles.samples = "CYCLES", 1
    try:
        assert bpy.ops.object.bake(type="NORMAL", use_clear=False, margin=0) == {"FINISHED"}
    finally:
        scene.cycles.samples = SPP
    cycles = _pixels(image).copy()
    scene.render.engine = Stopper.bl_idname
    Stopper.said.clear()
    assert bpy.ops.object.bake(type="NORMAL", use_clear=False, margin=0) == {"FINISHED"}
    covered = cycles[:, 3] >= 0.0
    assert np.abs(_pixels(image)[covered, :3] - cycles[covered, :3]).max() > 0.1
    assert Stopper.said[-1] == (f"the Normal bake ignores the Bump and Normal Map nodes of "
                                f"{ball.data.materials[0].name}: bake with Cycles to "
                                "include them")  # fmt: skip


def test_other_passes_are_refused_by_name(scene) -> None:
    ball = scene.objects["Ball"]
    _image_target(ball)
    _select(scene, ball)
    scene.render.engine = "SCENESORT"
    with pytest.raises(RuntimeError, match="scenesort AO bakes Ambient Occlusion and Normal "
                                           "only, not Emit"):  # fmt: skip
        bpy.ops.object.bake(type="EMIT")


def test_blender_refuses_an_object_without_uvs_with_its_own_message(scene) -> None:
    mesh = grid_mesh("NoUV", 2, 1.0)
    obj = add_object(scene, "NoUV", mesh, (5.0, 5.0, 0.0))
    try:
        _image_target(obj)
        _select(scene, obj)
        scene.render.engine = "SCENESORT"
        with pytest.raises(RuntimeError, match="No active UV layer found in the object"):
            bpy.ops.object.bake(type="AO")
    finally:
        bpy.data.objects.remove(obj)


def test_esc_cancels_the_bake_and_its_job(scene) -> None:
    """test_break() turning true while the bake's job runs cancels the job (benchmarks/
    bake.py measures how soon)."""
    ball = scene.objects["Ball"]
    image = _image_target(ball, 512)
    _select(scene, ball)
    scene.render.engine, scene.scenesort.spp = Stopper.bl_idname, 4096
    Stopper.said.clear()
    try:
        bpy.ops.object.bake(type="AO", use_clear=False, margin=0)
    finally:
        scene.scenesort.spp = SPP
    assert any("Bake cancelled" in line for line in Stopper.said), Stopper.said[-3:]
    assert re.search(r"DELETE /v1/jobs/[0-9a-f]+", service.log_path().read_text())
    # Blender writes whatever the engine left (RE_bake_engine cannot fail): 0 on the
    # covered texels, the rest untouched.
    assert set(np.unique(_pixels(image))) == {-1.0, 0.0}


def test_the_info_line_says_what_the_bake_achieved(scene) -> None:
    ball = scene.objects["Ball"]
    _image_target(ball)
    _select(scene, ball)
    scene.render.engine = Stopper.bl_idname
    Stopper.said.clear()
    scene.scenesort.spp = 16
    try:
        Stopper.stopped = lambda self: False  # type: ignore[method-assign]
        assert bpy.ops.object.bake(type="AO") == {"FINISHED"}
    finally:
        del Stopper.stopped
        scene.scenesort.spp = SPP
    line = Stopper.said[-1]
    assert re.match(r"baked [\d,]+ texels of 'Ball' \| [\d,]+ triangles \| .*est\. RMSE "
                    r"[\d.]+ \| spp 16\.0 mean, 16 max \| .* \| cpu$", line), line
    assert math.isclose(bpy.context.window_manager.scenesort.last_spp_mean, 16.0)
