"""Passes that follow the view layer's toggles, headless with a real service, against
Cycles' own passes of the same scene at pixel centres: Normal, Position, Object and
Material Index (a collection instance included) and the Denoising Data the compositor's
Denoise node takes."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import bpy
import numpy as np
import pytest
from blender_scenes import add_camera, add_object, box_mesh, grid_mesh
from cycles_reference import channel, clean_pixels, exr_channels, write_cycles_ao

import addon
from addon import engine, prefs

WIDTH, HEIGHT = 64, 48
TOGGLES = ("use_pass_z", "use_pass_normal", "use_pass_position", "use_pass_object_index",
           "use_pass_material_index")


@pytest.fixture(scope="module")
def scene() -> Iterator[bpy.types.Scene]:
    """A floor, a cube and a collection instance of a smaller cube, each with its own
    Pass Index and materials with theirs (the cube's faces in three slots, the last
    empty; the instanced cube's material linked to its object); the view layer's Normal,
    Position, Object and Material Index and Denoising Data on."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon.register()
    scn = bpy.context.scene
    add_object(scn, "Floor", grid_mesh("Floor", 4, 8.0)).pass_index = 1
    add_object(scn, "Cube", box_mesh("Cube", size=1.0), (-0.9, 0.3, 0.55)).pass_index = 2
    group = bpy.data.collections.new("Group")
    small = bpy.data.objects.new("Small", box_mesh("Small", size=0.7))
    small.pass_index = 3
    group.objects.link(small)
    holder = bpy.data.objects.new("Holder", None)
    holder.instance_type, holder.instance_collection = "COLLECTION", group
    holder.location, holder.pass_index = (1.0, 0.0, 0.4), 4
    scn.collection.objects.link(holder)
    materials = {name: bpy.data.materials.new(name) for name in ("F", "A", "B", "D", "O")}
    for index, mat in enumerate(materials.values(), start=5):
        mat.pass_index = index
    scn.objects["Floor"].data.materials.append(materials["F"])
    cube = scn.objects["Cube"].data
    for name in ("A", "B", None):
        cube.materials.append(materials.get(name))
    for face in cube.polygons:  # the top B, the front A, the others (a side seen) empty
        face.material_index = 1 if face.normal.z > 0.5 else 0 if face.normal.y < -0.5 else 2
    small.data.materials.append(materials["D"])
    small.material_slots[0].link = "OBJECT"  # the object's material, not its mesh's
    small.material_slots[0].material = materials["O"]
    add_camera(scn, (0.0, -5.5, 3.0), (math.radians(62), 0.0, 0.0), WIDTH, HEIGHT)
    scn.world = bpy.data.worlds.new("World")
    scn.scenesort.spp = 16
    # the pixel-centre filter of the Cycles judge (a test below sets Cycles' default)
    scn.cycles.pixel_filter_type, scn.cycles.filter_width = "GAUSSIAN", 0.01
    layer = scn.view_layers[0]
    for toggle in TOGGLES:
        setattr(layer, toggle, True)
    layer.cycles.denoising_store_passes = True
    prefs.preferences(bpy.context).start_on_render = True
    try:
        yield scn
    finally:
        addon.unregister()


def render_multilayer(scene: bpy.types.Scene, engine_name: str, path: Path) -> dict:
    """F12 with `engine_name` into a multilayer EXR: its channels by full name."""
    if engine_name == "CYCLES":
        write_cycles_ao(scene, path, 4)
    else:
        scene.render.engine = engine_name
        fmt = scene.render.image_settings
        if hasattr(fmt, "media_type"):  # Blender 5 chooses a multilayer file by media type
            fmt.media_type = "MULTI_LAYER_IMAGE"
        else:
            fmt.file_format = "OPEN_EXR_MULTILAYER"
        fmt.color_depth = "32"
        scene.render.film_transparent = True
        scene.render.filepath = str(path)
        assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
    return exr_channels(path.with_suffix(".exr"))


def test_passes_follow_the_view_layer(scene) -> None:
    """Registered for the compositor as the toggles say, in Cycles' names."""
    names = [p.blender[0] for p in engine.image.wanted_passes(scene.view_layers[0])]
    assert names == ["Depth", "Normal", "Position", "IndexOB", "IndexMA", "Denoising Normal",
                     "Denoising Albedo", "Denoising Depth"]
    layer = scene.view_layers[0]
    layer.use_pass_position = False
    layer.cycles.denoising_store_passes = False
    try:
        names = [p.blender[0] for p in engine.image.wanted_passes(layer)]
        assert names == ["Depth", "Normal", "IndexOB", "IndexMA"]
    finally:
        layer.use_pass_position = True
        layer.cycles.denoising_store_passes = True


def test_passes_match_cycles(scene, tmp_path) -> None:
    ours = render_multilayer(scene, "SCENESORT", tmp_path / "ours")
    cycles = render_multilayer(scene, "CYCLES", tmp_path / "cycles")
    alpha, our_alpha = channel(cycles, "Combined.A"), channel(ours, "Combined.A")
    assert np.mean(alpha != our_alpha) < 0.02  # pixel centres both (a 0.01 px filter)
    clean = clean_pixels(alpha == 1.0) & clean_pixels(our_alpha == 1.0)
    assert clean.sum() > 500
    for name in ("Normal", "Position"):
        for axis in "XYZ":
            a, b = channel(ours, f"{name}.{axis}"), channel(cycles, f"{name}.{axis}")
            np.testing.assert_allclose(a[clean], b[clean], atol=2e-3, err_msg=name + axis)
            assert np.all(a[our_alpha == 0] == 0.0)
    index = channel(ours, "IndexOB.X", "Object Index.X")  # Blender 5 writes full names
    np.testing.assert_array_equal(index[clean],
                                  channel(cycles, "IndexOB.X", "Object Index.X")[clean])
    assert {1.0, 2.0, 3.0} <= set(np.unique(index[clean]).tolist())
    material = channel(ours, "IndexMA.X", "Material Index.X")
    np.testing.assert_array_equal(material[clean],
                                  channel(cycles, "IndexMA.X", "Material Index.X")[clean])
    # the floor's, the cube's first two slots and its empty one, the instance's object's
    assert {5.0, 6.0, 7.0, 0.0, 9.0} <= set(np.unique(material[clean]).tolist())
    assert np.all(material[our_alpha == 0] == 0.0)
    for axis in "XYZ":
        np.testing.assert_array_equal(channel(ours, f"Denoising Normal.{axis}"),
                                      channel(ours, f"Normal.{axis}"))
    albedo = channel(ours, "Denoising Albedo.R")
    assert np.array_equal(albedo, our_alpha) and {"Denoising Albedo.R"} <= set(
        k.split("ViewLayer.")[-1] for k in cycles)
    np.testing.assert_array_equal(channel(ours, "Denoising Depth.Z"), channel(ours, "Depth.Z"))


def test_the_normal_pass_goes_through_the_pixel_filter_as_cycles(scene, tmp_path) -> None:
    """At Cycles' default filter (Blackman-Harris 1.5 px) the Normal pass does not make F12
    fall back to pixel centres: alpha is the filtered coverage (edges in between), and the
    Normal pass, the mean of the samples' normals, is Cycles' to within 1.25x the RMSE
    between two Cycles renders of other seeds, over every covered pixel."""
    cycles = scene.cycles
    kept = cycles.pixel_filter_type, cycles.filter_width
    film = ("BLACKMAN_HARRIS", 1.5)
    try:
        cycles.pixel_filter_type, cycles.filter_width = film
        ours = render_multilayer(scene, "SCENESORT", tmp_path / "ours")
        refs = []
        for seed in (11, 12):
            write_cycles_ao(scene, tmp_path / f"cycles{seed}", scene.scenesort.spp, seed=seed,
                            film=film)
            refs.append(exr_channels(tmp_path / f"cycles{seed}.exr"))
    finally:
        cycles.pixel_filter_type, cycles.filter_width = kept
    alpha = channel(ours, "Combined.A")
    assert ((alpha > 0.05) & (alpha < 0.95)).sum() > 20
    covered = (alpha > 0) | (channel(refs[0], "Combined.A") > 0)

    def normals(channels: dict) -> np.ndarray:
        return np.stack([channel(channels, f"Normal.{axis}") for axis in "XYZ"], axis=-1)

    def rmse(x: np.ndarray, y: np.ndarray) -> float:
        return float(np.sqrt(np.mean(np.sum((x - y) ** 2, axis=-1)[covered])))

    own = rmse(normals(refs[1]), normals(refs[0]))
    assert 0.0 < rmse(normals(ours), normals(refs[0])) <= 1.25 * own


def test_without_the_z_pass_no_depth_is_traced(scene, tmp_path, monkeypatch) -> None:
    """Z, Denoising Data, Position, Object and Material Index off: the result holds no
    Depth, and
    the job traced none (the camera rays' second, closest-hit trace is what it costs)."""
    from addon import pipeline

    outcomes = []
    real = pipeline.render_job
    monkeypatch.setattr(pipeline, "render_job",
                        lambda *a, **k: outcomes.append(real(*a, **k)) or outcomes[-1])
    layer = scene.view_layers[0]
    off = ("use_pass_z", "use_pass_position", "use_pass_object_index",
           "use_pass_material_index")
    for name in off:
        setattr(layer, name, False)
    layer.cycles.denoising_store_passes = False
    try:
        names = set(render_multilayer(scene, "SCENESORT", tmp_path / "no_z"))
    finally:
        for name in off:
            setattr(layer, name, True)
        layer.cycles.denoising_store_passes = True
    assert not any(".Depth." in n or "Denoising" in n for n in names), names
    assert outcomes[-1].depth is None and "depth" not in outcomes[-1].timings_ms
