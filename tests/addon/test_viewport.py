"""The Rendered viewport headless: the engine accepted for RENDERED shading, the region's
view as the service's camera (checked against Blender's own projection of a camera), and
the view session with real depsgraphs and a real service: what each kind of update
exports, sends and builds, cancellation, and its image against an F12 of the same view."""

from __future__ import annotations

import math
from collections.abc import Iterator

import bpy
import numpy as np
import pytest
from blender_scenes import add_camera, add_object, box_mesh, f12, grid_mesh

import addon
from addon import camera, pipeline, prefs, viewport
from scenesort import kernels

WIDTH, HEIGHT = 64, 40


@pytest.fixture(scope="module")
def scene() -> Iterator[bpy.types.Scene]:
    """A floor, a cube and two linked duplicates of a bumpy grid, seen by a camera."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon.register()
    scn = bpy.context.scene
    add_object(scn, "Floor", grid_mesh("Floor", 4, 8.0))
    add_object(scn, "Cube", box_mesh("Cube", size=1.0), (-1.0, 0.5, 0.55))
    bumps = grid_mesh("Bumps", 6, 1.2)
    for k, v in enumerate(bumps.vertices):
        v.co.z = 0.1 * math.sin(k)
    add_object(scn, "BumpsA", bumps, (1.0, 0.0, 0.4))
    add_object(scn, "BumpsB", bumps, (1.4, 1.2, 0.6))
    add_camera(scn, (0.0, -5.0, 3.0), (math.radians(60), 0.0, 0.0), WIDTH, HEIGHT)
    scn.world = bpy.data.worlds.new("World")
    scn.render.engine = "SCENESORT"
    scn.scenesort.viewport_spp = 8
    # F12 through the pixel-centre filter, as the viewport renders
    scn.cycles.pixel_filter_type, scn.cycles.filter_width = "GAUSSIAN", 0.01
    prefs.preferences(bpy.context).start_on_render = True
    try:
        yield scn
    finally:
        addon.unregister()


def test_rendered_shading_is_offered(scene) -> None:
    scene.display.shading.type = "RENDERED"  # refused for an engine without view_draw
    assert scene.display.shading.type == "RENDERED"
    scene.display.shading.type = "SOLID"


def blender_projection(scene, obj) -> tuple:
    """Blender's own world-to-view matrix and projection of camera `obj` (as a 3D view
    through it has them)."""
    depsgraph = bpy.context.evaluated_depsgraph_get()
    projection = obj.calc_matrix_camera(depsgraph, x=WIDTH, y=HEIGHT)
    return obj.matrix_world.inverted(), projection


def segments(cam: kernels.Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each ray's clipped segment: start point, unit direction, length."""
    o, d, tmin, tmax = cam.rays()
    norm = np.linalg.norm(d, axis=1)
    return o + tmin[:, None] * d, d / norm[:, None], (tmax - tmin) * norm


@pytest.mark.parametrize("kind", ["PERSP", "ORTHO"])
def test_region_camera_is_blenders_projection(scene, kind) -> None:
    """The view made from Blender's projection of a camera (shifted, sensor fit vertical)
    gives the rays of the camera itself: the same start points and directions, and the
    same lengths but for the float32 projection's far plane (0.1%)."""
    obj = scene.camera
    data = obj.data
    saved = (data.type, data.shift_x, data.shift_y, data.sensor_fit, data.ortho_scale)
    data.type, data.shift_x, data.shift_y, data.sensor_fit = kind, 0.1, -0.05, "VERTICAL"
    data.ortho_scale = 5.0
    try:
        ours = kernels.Camera.from_dict(viewport.region_camera(
            *blender_projection(scene, obj), WIDTH, HEIGHT))
        theirs = kernels.Camera.from_dict(camera.camera_dict(scene))
    finally:
        data.type, data.shift_x, data.shift_y, data.sensor_fit, data.ortho_scale = saved
    (start_a, dir_a, len_a), (start_b, dir_b, len_b) = segments(ours), segments(theirs)
    np.testing.assert_allclose(start_a, start_b, atol=1e-5 * np.abs(start_b).max())
    np.testing.assert_allclose(dir_a, dir_b, atol=1e-6)
    np.testing.assert_allclose(len_a, len_b, rtol=1e-3)


def test_degenerate_views_are_refused_in_words() -> None:
    with pytest.raises(ValueError, match="0x40 pixels"):
        viewport.region_camera(np.eye(4), np.eye(4), 0, 40)
    with pytest.raises(ValueError, match="degenerate"):
        viewport.region_camera(np.eye(4), np.zeros((4, 4)), 64, 40)


def test_the_error_estimate_is_the_binomial_one() -> None:
    """sqrt(m (1 - m) / (n - 1)) over covered pixels: 0.5 everywhere at 5 samples is 0.25;
    unknown at 1 sample (0 or 1 everywhere says nothing of the variance)."""
    mean = np.array([0.5, 0.5, 1.0, 0.0], np.float32)
    covered = np.array([1, 1, 0, 0], np.float32)
    assert viewport.binomial_rmse(mean, covered, 5) == 0.25
    assert viewport.binomial_rmse(mean, np.zeros(4, np.float32), 5) is None
    assert viewport.binomial_rmse(np.ones(4, np.float32), covered, 1) is None


def test_schedule_doubles_to_the_samples() -> None:
    assert viewport.schedule(1) == [1]
    assert viewport.schedule(8) == [1, 1, 2, 4]
    assert viewport.schedule(10) == [1, 1, 2, 4, 2]


def camera_view(scene) -> dict:
    return viewport.region_view(*blender_projection(scene, scene.camera), WIDTH, HEIGHT, 1)


class Watch:
    """A view session fed the real depsgraph's updates (as Blender calls view_update)."""

    def __init__(self, scene) -> None:
        self.session = viewport.ViewSession(prefs.target(bpy.context))
        self.rounds = self.checks = 0
        self.sent: list[str] = []
        self.session.update_scene(bpy.context.evaluated_depsgraph_get(), first=True)
        self.session.look(camera_view(scene))
        bpy.app.handlers.depsgraph_update_post.append(self.updated)

    def updated(self, scene, depsgraph) -> None:  # noqa: ANN001
        self.session.update_scene(depsgraph)

    def settle(self) -> list[pipeline.Outcome]:
        """Wait for the rounds; the outcomes of the rounds since the last settling (and
        in `sent`, the meshes their scene checks uploaded)."""
        self.session.wait(60)
        assert self.session.error is None, self.session.error
        rounds, checks = self.session.outcomes[self.rounds:], self.session.checks[self.checks:]
        self.rounds, self.checks = len(self.session.outcomes), len(self.session.checks)
        self.sent = [r for o in checks for r in o.requests if r.startswith("PUT /v1/meshes")]
        return rounds

    def close(self) -> None:
        bpy.app.handlers.depsgraph_update_post.remove(self.updated)
        self.session.stop()
        self.session.wait(10)


def built(outcomes, kind: str) -> set[str]:
    return {m for o in outcomes if o.build_report for m in o.build_report[kind]}


def test_each_update_does_only_what_it_must(scene) -> None:
    watch = Watch(scene)
    try:
        first = watch.settle()
        # a first look at a quarter of the size, then 1, 1, 2, 4 samples at full size
        assert [(o.size, o.spp_max) for o in first] == [
            ((WIDTH // 4, HEIGHT // 4), 1), *(((WIDTH, HEIGHT), n) for n in (1, 1, 2, 4))]
        assert all(o.depth is None for o in first)  # no Z pass traced for the viewport
        assert watch.session.frame().spp == 8 and watch.session.frame().done
        exports = watch.session.exports
        # a view change: traced again, nothing exported, sent or built
        watch.session.look(viewport.region_view(*blender_projection(scene, scene.camera),
                                                WIDTH // 2, HEIGHT // 2, 1))
        moved_view = watch.settle()
        assert moved_view and watch.session.exports == exports
        assert not watch.sent and not built(moved_view, "built")
        # a material's colour: nothing at all (assigning one is a geometry update for
        # Blender: read again, but the same instance list, so nothing is traced)
        red = bpy.data.materials.new("Red")
        scene.objects["Cube"].active_material = red
        bpy.context.view_layer.update()
        assert not watch.session.refining
        exports = watch.session.exports
        red.diffuse_color = (1.0, 0.0, 0.0, 1.0)
        bpy.context.view_layer.update()
        assert not watch.session.refining and watch.session.exports == exports
        # one object moved: the instance list only, no mesh read, sent or built
        read = dict(watch.session.scene.meshes)
        scene.objects["BumpsB"].location.x += 0.3
        bpy.context.view_layer.update()
        moved = watch.settle()
        assert all(mesh is read[name] for name, mesh in watch.session.scene.meshes.items())
        assert moved and not watch.sent and not built(moved, "built")
        assert not built(moved, "refit")
        # an edit of the shared mesh's vertices: that mesh sent and refit, no other
        bumps = bpy.data.meshes["Bumps"]
        bumps.vertices[0].co.z += 0.2
        bumps.update()
        bpy.context.view_layer.update()
        edited = watch.settle()
        assert len(watch.sent) == 1 and len(built(edited, "refit")) == 1
        assert not built(edited, "built")
    finally:
        watch.close()


def test_a_viewport_target_error_refines_adaptively(scene) -> None:
    """With a Viewport Target Error T: the preview and 1-sample rounds, then the final
    render's adaptive jobs to 4T, 2T and T, the last image's estimate within T."""
    scene.scenesort.viewport_target_error = 0.03
    watch = Watch(scene)
    try:
        rounds = watch.settle()
        frame = watch.session.frame()
        text = viewport.status_text(watch.session)
    finally:
        scene.scenesort.viewport_target_error = 0.0
        watch.close()
    assert [o.spp_max for o in rounds[:2]] == [1, 1]
    estimates = [o.rmse_estimate for o in rounds[2:]]
    assert len(estimates) == 3 and estimates[-1] <= 0.03 < estimates[0]
    assert frame.done and frame.rmse == estimates[-1] and "target 0.0300 | done" in text


def test_a_new_view_cancels_the_rounds_in_flight(scene) -> None:
    scene.scenesort.viewport_spp = 512
    watch = Watch(scene)
    try:
        while not watch.session.outcomes:  # the first round came back: the rest runs
            watch.session.wait(0.01)
        task = watch.session._task
        watch.session.look(viewport.region_view(*blender_projection(scene, scene.camera),
                                                WIDTH, HEIGHT, 2))
        task.join(5)
        assert task.done and task.cancelled
    finally:
        scene.scenesort.viewport_spp = 8
        watch.close()


def test_the_view_is_an_f12_of_it(scene, tmp_path) -> None:
    """At the same samples the viewport's image through the camera is F12's but for
    noise: the same pixels covered, no bias, their difference the two renders' noise."""
    scene.scenesort.viewport_spp = scene.scenesort.spp = 64
    watch = Watch(scene)
    try:
        watch.settle()
        frame = watch.session.frame()
    finally:
        watch.close()
        scene.scenesort.viewport_spp = 8
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    scene.render.film_transparent = True
    try:
        rgba = f12(scene, tmp_path / "f12")
    finally:
        scene.render.film_transparent = False
    ours = frame.rgba[::-1, :, 0]
    covered = rgba[..., 3] > 0
    assert covered.mean() > 0.5 and np.mean((ours > 0) != covered) < 0.01
    d = (ours - rgba[..., 0])[covered]
    assert abs(d.mean()) < 0.01 and np.sqrt(np.mean(d**2)) < 0.08, (d.mean(), d.std())
