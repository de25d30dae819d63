"""The `scenesort AO` render engine, headless: F12 and Ctrl-F12 through Blender's own
render operator, against a real service that the first render starts by itself.

Images come back through the files Blender writes (32-bit EXR: linear, no view
transform); the passes, the status-bar lines and Esc through a subclass of the engine
(`Probe`) that keeps what Blender holds after the engine filled the result.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import ClassVar

import bpy
import httpx
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
    free_port,
    grid_mesh,
)

import addon
from addon import camera, engine, export, pipeline, prefs, service
from tests.waiting import until

WIDTH, HEIGHT = 40, 30
FLOOR_TRIANGLES, BOX_TRIANGLES = 2 * 8 * 8, 12


class Probe(engine.AoEngine, bpy.types.RenderEngine):
    """The engine, keeping its passes and status lines; `stop_when(engine)` plays Esc."""

    bl_idname = "SCENESORT_PROBE"
    bl_label = "scenesort AO (probe)"
    bl_use_preview = False
    passes: ClassVar[dict[str, np.ndarray]] = {}
    stats: ClassVar[list[str]] = []
    steps: ClassVar[list[str]] = []
    stop_when: ClassVar[Callable[[engine.AoEngine], bool] | None] = None

    def fill(self, result, passes) -> None:  # noqa: ANN001 - what Blender then holds
        super().fill(result, passes)
        size = (result.resolution_y, result.resolution_x)
        for p in result.layers[0].passes:
            Probe.passes[p.name] = np.array(p.rect, np.float32).reshape(*size, p.channels)

    def show(self, text: str) -> None:
        Probe.stats.append(text)
        super().show(text)

    def stopped(self) -> bool:
        if self.task is not None:
            Probe.steps[:] = self.task.steps
        return bool(Probe.stop_when and Probe.stop_when(self)) or super().stopped()


@pytest.fixture(scope="module")
def live() -> Iterator[bpy.types.Scene]:
    """A floor with a box on it and a camera; the engine picked in Render Properties."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon.register()
    bpy.utils.register_class(Probe)
    scene = bpy.context.scene
    add_object(scene, "Floor", grid_mesh("Floor", 8, 8.0))
    add_object(scene, "Box", box_mesh("Box", size=1.5), (0.0, 0.0, 0.75))
    add_camera(scene, (0.0, -7.0, 4.0), (math.radians(60), 0.0, 0.0), WIDTH, HEIGHT)
    scene.scenesort.ao_distance, scene.scenesort.spp, scene.scenesort.seed = 2.0, 4, 1
    scene.render.engine = "SCENESORT"
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    layer = scene.view_layers[0]  # Passes > Data > Z and Ambient Occlusion
    layer.use_pass_z = layer.use_pass_ambient_occlusion = True
    try:
        yield scene
    finally:
        proc = service._process
        bpy.utils.unregister_class(Probe)
        addon.unregister()
        assert proc is None or proc.poll() is not None, "unregister left the service running"
        assert "SCENESORT" not in bpy.types.RENDER_PT_format.COMPAT_ENGINES  # given back


@pytest.fixture
def probe(live) -> Iterator[bpy.types.Scene]:
    """The scene rendered by `Probe`, with a fresh record."""
    Probe.passes.clear(), Probe.stats.clear(), Probe.steps.clear()
    Probe.stop_when = None
    live.render.engine = Probe.bl_idname
    try:
        yield live
    finally:
        live.render.engine = "SCENESORT"
        Probe.stop_when = None


def _direct(scene: bpy.types.Scene) -> tuple[np.ndarray, np.ndarray]:
    """AO (a miss counts 1) and coverage of the scene's camera from the engine itself
    (`direct_film`: through the scene's pixel filter, or pixel centres where the options
    fall back, denoised as the Sampling panel's Denoise says)."""
    depsgraph = bpy.context.evaluated_depsgraph_get()
    return direct_film(scene, export.export_scene(depsgraph),
                       camera.camera_dict(scene, depsgraph))


def test_engine_is_selectable_with_its_passes(live) -> None:
    assert engine.SCENESORT_RE_ao.bl_label == "scenesort AO"
    assert live.render.engine == "SCENESORT"  # Blender accepts only registered engines
    assert "SCENESORT" in bpy.types.RENDER_PT_format.COMPAT_ENGINES  # output settings shown


def test_stats_line_reports_what_the_render_achieved() -> None:
    """The status bar and metadata line carries the job's estimated RMSE, mean and
    largest spp and rays, and the film; an unknown estimate shows as '-'."""
    from addon.connection import Connection

    outcome = pipeline.Outcome(rmse_estimate=0.0123, spp_mean=40.25, spp_max=256,
                               rays=123456, render_ms=10.0,
                               connection=Connection(None, {"device": "cuda:0"}, False))
    line = engine.stats_line(outcome, 1000)
    assert "est. RMSE 0.0123" in line and "spp 40.2 mean, 256 max" in line
    assert line.endswith("123,456 rays | film - | cuda:0")
    film = pipeline.Outcome(film="BLACKMAN_HARRIS 1.5 px")
    assert "| film BLACKMAN_HARRIS 1.5 px |" in engine.stats_line(film, 1000)
    assert "est. RMSE -" in engine.stats_line(pipeline.Outcome(), 1000)


def test_f12_combined_is_the_engines_ao_with_zero_background(live, tmp_path) -> None:
    """F12 starts the service itself; Combined RGB equals a direct engine call's AO on the
    same rays, 0 where the ray missed (Cycles' AO pass); alpha 1 without Film Transparent."""
    prefs.preferences(bpy.context).start_on_render = True
    live.render.film_transparent = False
    assert not service.running()
    rgba = f12(live, tmp_path / "still")
    assert service.running()
    props = live.scenesort  # the build's timings reach the panel's table
    assert props.has_build and props.build_triangles == FLOOR_TRIANGLES + BOX_TRIANGLES
    ao, coverage = _direct(live)
    hit = coverage > 0
    assert rgba.shape == (HEIGHT, WIDTH, 4)
    assert 0.3 < hit.mean() < 1.0  # some sky above the floor
    assert ((coverage > 0) & (coverage < 1)).any()  # the scene's filter smooths its edges
    np.testing.assert_array_equal(rgba[..., 0], ao_pass(ao, coverage))
    np.testing.assert_array_equal(rgba[..., 1], rgba[..., 0])
    np.testing.assert_array_equal(rgba[..., 2], rgba[..., 0])
    assert np.all(rgba[..., 3] == 1.0)
    assert rgba[hit, 0].std() > 0.05  # shaded, not flat


def test_denoise_checkbox_denoises_f12_and_says_so(probe, tmp_path) -> None:
    """Sampling > Denoise: F12's Combined is the engine's denoised AO (not the raw one)
    and the stats line says the estimate is from before denoising."""
    probe.scenesort.use_denoising = True
    try:
        rgba = f12(probe, tmp_path / "denoised")
        ao, hit = _direct(probe)
    finally:
        probe.scenesort.use_denoising = False
    np.testing.assert_allclose(rgba[..., 0], ao_pass(ao, hit), atol=1e-6)
    raw, _ = _direct(probe)  # without denoising: through the filter
    assert np.abs(rgba[..., 0] - ao_pass(raw, hit)).max() > 0.01  # it did denoise
    assert any("before denoising" in line for line in Probe.stats), Probe.stats
    # the denoiser works on pixel centres, and the stats line says so
    assert any("film pixel centres: denoise" in line for line in Probe.stats), Probe.stats


def test_resolution_percentage_renders_fewer_pixels_of_the_same_view(live, tmp_path) -> None:
    live.render.resolution_percentage = 50
    try:
        rgba = f12(live, tmp_path / "half")
        ao, coverage = _direct(live)
    finally:
        live.render.resolution_percentage = 100
    assert rgba.shape == (HEIGHT // 2, WIDTH // 2, 4) == (*ao.shape, 4)
    np.testing.assert_array_equal(rgba[..., 0], ao_pass(ao, coverage))


def test_film_transparent_background_alpha_is_exactly_zero(live, tmp_path) -> None:
    live.render.film_transparent = True
    try:
        rgba = f12(live, tmp_path / "transparent")
    finally:
        live.render.film_transparent = False
    _, coverage = _direct(live)
    np.testing.assert_array_equal(rgba[..., 3], coverage)
    assert np.all(rgba[coverage == 0] == 0.0)


def test_passes_ao_and_depth(probe, tmp_path) -> None:
    """AO is Combined's grey; Depth is camera-space Z at the pixel centre (1e10 on
    background): the floor right below the view's centre lies about |camera - floor
    point| * cos away. With Film > Transparent, AO is 0 where no filtered sample hit, and
    every pixel whose centre hit is covered."""
    probe.render.film_transparent = True
    try:
        f12(probe, tmp_path / "passes")
    finally:
        probe.render.film_transparent = False
    passes = Probe.passes
    assert set(passes) == {"Combined", "AO", "Depth"}
    combined, ao, depth = passes["Combined"], passes["AO"][..., 0], passes["Depth"][..., 0]
    np.testing.assert_array_equal(ao, combined[..., 0])
    hit, covered = depth < 1e10, combined[..., 3] > 0
    assert (~hit).any() and hit.any() and not (hit & ~covered).any()
    assert np.all(ao[~covered] == 0.0)
    # The centre pixel's ray (60 degrees from straight down) meets the floor (z = 0) at
    # ray length 4 / cos(60) = 8; its camera-space depth is that length (it is the axis).
    centre = depth[HEIGHT // 2 - 1 : HEIGHT // 2 + 1, WIDTH // 2 - 1 : WIDTH // 2 + 1]
    assert np.all((centre > 6.0) & (centre < 8.0 + 1e-3))  # the box (nearer) or the floor
    stats = " ".join(Probe.stats)
    assert f"{FLOOR_TRIANGLES + BOX_TRIANGLES:,} triangles" in stats
    assert re.search(r"build [\d.]+ ms", stats) and re.search(r"trace [\d.]+ ms", stats)


def test_animation_writes_each_frame_through_blenders_output(live, tmp_path) -> None:
    """Ctrl-F12: Blender numbers and writes the files itself, with the render's build and
    trace times in their metadata; the box moves per frame."""
    box = bpy.data.objects["Box"]
    box.location.x = -1.0
    box.keyframe_insert("location", frame=1)
    box.location.x = 1.0
    box.keyframe_insert("location", frame=3)
    try:
        images = ctrl_f12(live, tmp_path)
    finally:
        box.animation_data_clear()
        box.location.x = 0.0
        live.frame_set(1)
    frames = [np.asarray(img) for img in images]
    assert all(f.shape[:2] == (HEIGHT, WIDTH) for f in frames)
    assert not np.array_equal(frames[0], frames[2])  # each frame's own depsgraph
    note = images[0].text["scenesort"]  # the render's metadata, in the file
    triangles = FLOOR_TRIANGLES + BOX_TRIANGLES
    pattern = rf"{triangles} triangles \| build [\d.]+ ms.* \| trace [\d.]+ ms \| total .*"
    assert re.fullmatch(pattern, note), note


def test_render_visibility_and_render_levels_decide_what_renders(probe, tmp_path) -> None:
    """Hidden in the viewport but enabled for rendering: rendered. Disabled for rendering
    (object, collection) or excluded: not. A collection instance: rendered. Subdivision at
    its render level (2: 16 quads per face) though the viewport shows level 0. The panel's
    viewport export differs."""
    scene = probe
    hidden = add_object(scene, "Hidden", box_mesh("Hidden", 0.5), (2.0, 0.0, 0.25))
    hidden.hide_viewport = True
    hidden.hide_set(True)
    off = add_object(scene, "NoRender", box_mesh("NoRender", 0.5), (-2.0, 0.0, 0.25))
    off.hide_render = True
    subd = add_object(scene, "Subd", box_mesh("Subd", 0.5), (0.0, 2.0, 0.25))
    modifier = subd.modifiers.new("Subdivision", "SUBSURF")
    modifier.levels, modifier.render_levels = 0, 2
    collections = []
    for name in ("RenderOff", "Excluded"):
        coll = bpy.data.collections.new(name)
        scene.collection.children.link(coll)
        coll.objects.link(bpy.data.objects.new(name, box_mesh(name, 0.5)))
        collections.append(coll)
    collections[0].hide_render = True
    bpy.context.view_layer.layer_collection.children["Excluded"].exclude = True
    source = bpy.data.collections.new("Source")  # in no scene: only its instance renders
    source.objects.link(bpy.data.objects.new("Instanced", box_mesh("Instanced", 0.5)))
    instancer = add_object(scene, "Instancer", None, (0.0, -2.0, 0.25))
    instancer.instance_type, instancer.instance_collection = "COLLECTION", source
    try:
        f12(scene, tmp_path / "visibility")
        viewport = export.export_scene(bpy.context.evaluated_depsgraph_get()).triangles
    finally:
        for obj in (hidden, off, subd, instancer, *(c.objects[0] for c in collections),
                    source.objects[0]):  # fmt: skip
            bpy.data.objects.remove(obj)
        for coll in (*collections, source):
            bpy.data.collections.remove(coll)
    base = FLOOR_TRIANGLES + 2 * BOX_TRIANGLES  # the box and the instance
    expected = base + BOX_TRIANGLES + 6 * 16 * 2  # + Hidden + Subd at level 2
    assert f"{expected:,} triangles" in " ".join(Probe.stats), Probe.stats[-1]
    assert viewport == base + BOX_TRIANGLES  # viewport levels, viewport visibility


def _depth_top_first() -> np.ndarray:
    return Probe.passes["Depth"][::-1, :, 0]


def test_border_renders_that_part_of_the_frame(probe, tmp_path) -> None:
    """With a border the result is the border's rectangle; its Depth equals the whole
    frame's there. Crop to Border writes that rectangle, without crop the whole frame
    with nothing (alpha 0) outside it."""
    r = probe.render
    f12(probe, tmp_path / "whole")
    whole = _depth_top_first()
    r.use_border, r.film_transparent = True, True
    r.border_min_x, r.border_max_x, r.border_min_y, r.border_max_y = 0.25, 0.75, 0.2, 0.9
    window = camera.window(probe)
    x, y, w, h = window["x"], window["y"], window["width"], window["height"]
    try:
        r.use_crop_to_border = True
        cropped = f12(probe, tmp_path / "cropped")
        part = _depth_top_first()
        r.use_crop_to_border = False
        framed = f12(probe, tmp_path / "framed")
    finally:
        r.use_border, r.use_crop_to_border, r.film_transparent = False, False, False
    assert (w, h) == (20, 21) and part.shape == (h, w)
    np.testing.assert_array_equal(part, whole[y : y + h, x : x + w])
    assert cropped.shape == (h, w, 4) and framed.shape == (HEIGHT, WIDTH, 4)
    np.testing.assert_array_equal(framed[y : y + h, x : x + w], cropped)
    outside = np.ones((HEIGHT, WIDTH), bool)
    outside[y : y + h, x : x + w] = False
    assert np.all(framed[outside] == 0.0)


def test_pixel_aspect_two_to_one(probe, tmp_path) -> None:
    """Pixels twice as wide as tall see what every other column of a frame twice as wide
    sees, shifted half of its pixel (Blender's viewplane; the width is fitted)."""
    r, cam = probe.render, probe.camera.data
    r.pixel_aspect_x = 2.0
    try:
        f12(probe, tmp_path / "aspect")
    finally:
        r.pixel_aspect_x = 1.0
    wide = _depth_top_first()
    r.resolution_x, cam.shift_x = 2 * WIDTH, 1.0 / (4 * WIDTH)
    try:
        f12(probe, tmp_path / "fine")
    finally:
        r.resolution_x, cam.shift_x = WIDTH, 0.0
    fine = _depth_top_first()
    assert wide.shape == (HEIGHT, WIDTH) and fine.shape == (HEIGHT, 2 * WIDTH)
    np.testing.assert_allclose(wide, fine[:, ::2], rtol=1e-5)


def _cycles_depth(scene: bpy.types.Scene, path: Path) -> np.ndarray:
    """Cycles' camera-space depth at pixel centres (top row first): an emission of the
    Camera Data node's View Z Depth, 1 sample, a 0.01-pixel filter (BLENDER_FACTS.md)."""
    mat = bpy.data.materials.new("ViewZ")
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    nodes.clear()
    emission = nodes.new("ShaderNodeEmission")
    links.new(nodes.new("ShaderNodeCameraData").outputs["View Z Depth"], emission.inputs[1])
    links.new(emission.outputs[0], nodes.new("ShaderNodeOutputMaterial").inputs["Surface"])
    layer, render, cycles = bpy.context.view_layer, scene.render, scene.cycles
    layer.material_override, render.engine = mat, "CYCLES"
    cycles.samples, cycles.use_adaptive_sampling, cycles.use_denoising = 1, False, False
    cycles.pixel_filter_type, cycles.filter_width = "GAUSSIAN", 0.01
    scene.view_settings.view_transform = "Standard"  # EXR holds the values themselves
    try:
        return f12(scene, path)[..., 0]
    finally:
        layer.material_override, render.engine = None, Probe.bl_idname
        bpy.data.materials.remove(mat)


def test_border_and_pixel_aspect_match_cycles(probe, tmp_path) -> None:
    """Blender's own renderer as the judge: with a border and pixels twice as tall as wide
    (pixel aspect 1:2, so AUTO fits the height: 40 < 2 * 30), the Depth pass equals
    Cycles' camera-space depth at the same pixel centres."""
    r = probe.render
    r.pixel_aspect_y, r.use_border, r.use_crop_to_border = 2.0, True, True
    r.border_min_x, r.border_max_x, r.border_min_y, r.border_max_y = 0.1, 0.8, 0.3, 1.0
    try:
        f12(probe, tmp_path / "ours")
        ours = _depth_top_first()
        theirs = _cycles_depth(probe, tmp_path / "cycles")
    finally:
        r.pixel_aspect_y, r.use_border, r.use_crop_to_border = 1.0, False, False
    assert ours.shape == theirs.shape == (21, 28)
    hit = ours < 1e10
    assert 0.2 < hit.mean() < 1.0  # floor, box and sky in the border
    assert np.array_equal(hit, theirs > 0)  # Cycles' world is black: 0 on background
    close = np.isclose(ours[hit], theirs[hit], rtol=1e-3)
    assert close.mean() > 0.97, np.abs(ours - theirs)[hit].max()  # a box edge may differ


def test_esc_cancels_the_services_job(probe, tmp_path) -> None:
    """test_break() turning true while the job runs cancels it on the service."""
    props = probe.scenesort
    Probe.stop_when = lambda eng: any(s.startswith("running: ao") for s in eng.task.steps)
    # 78M occlusion rays: many of the engine's rounds, so the job is caught running.
    props.spp, probe.render.resolution_percentage = 4096, 400
    try:
        probe.render.filepath = str(tmp_path / "cancelled")
        bpy.ops.render.render()
    finally:
        props.spp, probe.render.resolution_percentage = 4, 100
    assert any("cancelled" in line for line in Probe.stats), Probe.stats[-3:]
    deleted = re.findall(r"DELETE /v1/jobs/([0-9a-f]+)", service.log_path().read_text())
    assert deleted, "the engine never cancelled the job"
    job_id = deleted[-1]
    url = bpy.context.window_manager.scenesort.url or service.served_url()
    headers = {"Authorization": f"Bearer {service.token_for(url)}"}

    def ended() -> str | None:  # the job stops at the engine's next round
        state = httpx.get(f"{url}/v1/jobs/{job_id}", headers=headers).json()["state"]
        return None if state in {"queued", "running"} else state

    assert until(ended, f"job {job_id} to end", 60.0) == "cancelled"


def test_esc_during_a_bvh_build_gives_control_back_before_it_ends(probe, tmp_path) -> None:
    """Esc while the service builds a 2M-triangle scene's BVH (one request, which cannot
    be cut short): F12 ends before the service has answered it, the build goes on there
    and is kept (its answer reaches the service's log later)."""
    import bmesh

    mesh = bpy.data.meshes.new("Big")
    bm = bmesh.new()
    bmesh.ops.create_grid(bm, x_segments=1000, y_segments=1000, size=3.0)
    bm.to_mesh(mesh)
    bm.free()
    big = add_object(probe, "Big", mesh, (0.0, 0.0, -0.05))
    Probe.stop_when = lambda eng: any(s.startswith("building the BVH") for s in eng.task.steps)

    def answered() -> int:  # builds the service has answered (its log: once it runs)
        log = service.log_path()
        text = log.read_text() if log is not None else ""
        return len(re.findall(r"POST /v1/scenes/[0-9a-f]+/bvh -> 200", text))

    before = answered()
    try:
        probe.render.filepath = str(tmp_path / "cancelled")
        bpy.ops.render.render()
        assert answered() == before  # control came back while the service still built
        assert any("cancelled" in line for line in Probe.stats), Probe.stats[-3:]
        assert until(lambda: answered() > before or None, "the build's answer", 120.0)
    finally:
        bpy.data.objects.remove(big)
        bpy.data.meshes.remove(mesh)


def test_empty_scene_gives_a_transparent_image_and_says_so(probe, tmp_path) -> None:
    objects = [bpy.data.objects["Floor"], bpy.data.objects["Box"]]
    for obj in objects:
        obj.hide_render = True
    probe.render.film_transparent = True
    try:
        rgba = f12(probe, tmp_path / "empty")
    finally:
        for obj in objects:
            obj.hide_render = False
        probe.render.film_transparent = False
    assert rgba.shape == (HEIGHT, WIDTH, 4) and np.all(rgba == 0.0)
    assert np.all(Probe.passes["Depth"] == 1e10)
    assert "Nothing to render" in Probe.stats[-1]


def test_no_camera_and_a_panoramic_camera_are_clear_errors(live, tmp_path) -> None:
    live.render.filepath = str(tmp_path / "none")
    cam = live.camera
    live.camera = None
    try:
        with pytest.raises(RuntimeError, match="(?i)no camera"):
            bpy.ops.render.render()
    finally:
        live.camera = cam
    cam.data.type = "PANO"
    try:
        with pytest.raises(RuntimeError, match="only Perspective and Orthographic"):
            bpy.ops.render.render()
    finally:
        cam.data.type = "PERSP"


def test_a_stopped_or_unreachable_service_is_a_clear_error(live, tmp_path) -> None:
    live.render.filepath = str(tmp_path / "offline")
    preferences = prefs.preferences(bpy.context)
    assert bpy.ops.scenesort.server_stop() == {"FINISHED"}
    preferences.start_on_render = False
    try:
        with pytest.raises(RuntimeError, match="No scenesort service is running"):
            bpy.ops.render.render()
        preferences.server_url = f"http://127.0.0.1:{free_port()}"
        with pytest.raises(RuntimeError, match="No scenesort service is running at http"):
            bpy.ops.render.render()
    finally:
        preferences.start_on_render, preferences.server_url = True, ""


def test_engine_panels_show_for_the_engine_only(live) -> None:
    """Sampling and Film are the engine's own Render Properties panels (poll on the
    engine); the scenesort panel with its build timings stays in Render Properties."""
    from addon import panel

    for cls in (panel.SCENESORT_PT_sampling, panel.SCENESORT_PT_film):
        assert cls.bl_context == "render" and {"SCENESORT"} == cls.COMPAT_ENGINES
        assert cls.poll(bpy.context)
        live.render.engine = "CYCLES"
        try:
            assert not cls.poll(bpy.context)
        finally:
            live.render.engine = "SCENESORT"
    assert panel.SCENESORT_PT_render.bl_context == "render"


class _Layout:
    """Takes the UILayout calls of a panel's draw (Blender only draws with a window)."""

    use_property_split = False

    def __init__(self) -> None:
        self.props: list[tuple[object, str, str]] = []

    def column(self, align: bool = False) -> _Layout:
        return self

    def prop(self, owner: object, name: str, text: str = "") -> None:
        self.props.append((owner, name, text))

    def label(self, text: str = "", icon: str = "NONE") -> None:
        self.props.append((None, "label", text))


def test_engine_panels_draw_the_scenes_settings(live) -> None:
    from addon import panel

    drawn = {}
    for cls in (panel.SCENESORT_PT_sampling, panel.SCENESORT_PT_film):
        layout = _Layout()
        cls.draw(SimpleNamespace(layout=layout, source=cls.source, groups=cls.groups),
                 bpy.context)  # fmt: skip
        drawn.update({name: owner for owner, name, _ in layout.props if owner is not None})
    assert drawn == {"spp": live.scenesort, "target_error": live.scenesort,
                     "max_pixel_error": live.scenesort, "use_denoising": live.scenesort,
                     "ao_distance": live.scenesort, "seed": live.scenesort,
                     "viewport_spp": live.scenesort,
                     "viewport_target_error": live.scenesort,
                     "film_transparent": live.render}  # fmt: skip


def test_sampling_panel_shows_the_worlds_ao_distance(live) -> None:
    """AO Distance 0 means the World's: the Sampling panel shows that one too when the
    scene has a World (Cycles shows it in its Fast GI panel, not drawn for this engine)."""
    from addon import panel

    cls = panel.SCENESORT_PT_sampling

    def drawn() -> dict[str, object]:
        layout = _Layout()
        cls.draw(SimpleNamespace(layout=layout, source=cls.source, groups=cls.groups),
                 bpy.context)  # fmt: skip
        return {name: owner for owner, name, _ in layout.props if owner is not None}

    assert live.world is None and "distance" not in drawn()
    live.world = bpy.data.worlds.new("World")
    try:
        assert drawn()["distance"] == live.world.light_settings
    finally:
        bpy.data.worlds.remove(live.world)


def test_sampling_panel_names_the_device_of_the_last_f12(live, tmp_path) -> None:
    """After F12 the Sampling panel says which device traced it (the service's, which the
    Device preference decides); before any render it says nothing."""
    from addon import panel

    def labels() -> list[str]:
        layout = _Layout()
        cls = panel.SCENESORT_PT_sampling
        cls.draw(SimpleNamespace(layout=layout, source=cls.source, groups=cls.groups),
                 bpy.context)  # fmt: skip
        return [text for _, name, text in layout.props if name == "label"]

    status = bpy.context.window_manager.scenesort
    status.last_device = ""
    assert labels() == []
    f12(live, tmp_path / "device")
    assert status.last_device == "cpu"  # the live service's device: no GPU here
    assert labels() == ["Last render on cpu"]
