"""F12 with Render Properties > Performance > Persistent Data, headless with a real
service: a later F12 of an unchanged scene reads and hashes no mesh and renders the same
image; after each kind of change, what F12 sends is what a fresh export of the changed
scene holds, and an instance list reads again only the mesh that changed."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator

import bpy
import numpy as np
import pytest
from blender_scenes import add_camera, add_object, box_mesh, f12, grid_mesh, render_with_engine

import addon
from addon import export, persistent, pipeline

WIDTH, HEIGHT, SPP = 32, 24, 4


@pytest.fixture(scope="module")
def scene() -> Iterator[bpy.types.Scene]:
    """A floor, a box and a subdivided smooth box, Persistent Data on."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon.register()
    scn = bpy.context.scene
    add_object(scn, "Floor", grid_mesh("Floor", 6, 8.0))
    add_object(scn, "Box", box_mesh("Box", size=1.0), (-1.2, 0.0, 0.6))
    smooth = add_object(scn, "Smooth", box_mesh("Smooth", size=1.0), (1.2, 0.0, 0.6))
    smooth.data.shade_smooth()
    mod = smooth.modifiers.new("Subdivision", "SUBSURF")
    mod.levels = mod.render_levels = 2  # the viewport's export is the render's
    add_camera(scn, (0.0, -6.0, 3.5), (math.radians(62), 0.0, 0.0), WIDTH, HEIGHT)
    render_with_engine(scn, 1.5, SPP, 1)
    scn.render.use_persistent_data = True
    try:
        yield scn
    finally:
        addon.unregister()


class Record:
    """What each F12 exported (the scene it sent) and how many meshes it read from
    Blender, and how many scenes it hashed."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.sent: list[export.SceneMesh | export.InstanceExport] = []
        self.outcomes: list[pipeline.Outcome] = []
        self.reads = self.hashes = 0
        for name in ("export_scene", "export_instances"):
            monkeypatch.setattr(persistent, name, self._sending(getattr(persistent, name)))
        monkeypatch.setattr(export, "_read_mesh", self._counting(export._read_mesh, "reads"))
        monkeypatch.setattr(export, "content_id", self._counting(export.content_id, "hashes"))
        real = pipeline.render_job

        def job(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202 - the real job, recorded
            self.outcomes.append(real(*args, **kwargs))
            return self.outcomes[-1]

        monkeypatch.setattr(pipeline, "render_job", job)

    def _sending(self, real: Callable) -> Callable:
        def export_(depsgraph):  # noqa: ANN001, ANN202
            self.sent.append(real(depsgraph))
            return self.sent[-1]
        return export_

    def _counting(self, real: Callable, counter: str) -> Callable:
        def counted(*args):  # noqa: ANN002, ANN202
            setattr(self, counter, getattr(self, counter) + 1)
            return real(*args)
        return counted

    def f12(self, scene: bpy.types.Scene, path) -> tuple[np.ndarray, int, int]:  # noqa: ANN001
        """F12: (RGBA, meshes read, scenes hashed)."""
        self.reads = self.hashes = 0
        image = f12(scene, path)
        return image, self.reads, self.hashes


def fresh() -> export.SceneMesh:
    """The scene exported from a depsgraph of its own (the viewport's: same levels)."""
    return export.export_scene(bpy.context.evaluated_depsgraph_get())


def assert_same_scene(sent: export.SceneMesh, expected: export.SceneMesh) -> None:
    for name in ("vertices", "indices", "normals", "terminator_offsets"):
        a, b = getattr(sent, name), getattr(expected, name)
        assert (a is None) == (b is None), name
        if a is not None:
            np.testing.assert_array_equal(a, b, err_msg=name)


def test_a_later_f12_of_an_unchanged_scene_reads_and_hashes_no_mesh(scene, monkeypatch,
                                                                    tmp_path) -> None:
    record = Record(monkeypatch)
    scene.objects["Box"].location.z += 0.01  # a scene the service has not seen
    first, read, hashed = record.f12(scene, tmp_path / "first")
    assert read == 3 and hashed == 1
    again, read, hashed = record.f12(scene, tmp_path / "again")
    assert (read, hashed) == (0, 0)
    assert record.sent[1] is record.sent[0]
    assert "POST /v1/scenes" not in record.outcomes[1].requests  # no upload
    np.testing.assert_array_equal(again, first)
    scene.camera.location.x += 0.3  # the camera is not the scene
    moved, read, hashed = record.f12(scene, tmp_path / "camera")
    assert (read, hashed) == (0, 0)
    assert not np.array_equal(moved, first)


CHANGES: dict[str, Callable[[bpy.types.Scene], None]] = {
    "object moved": lambda s: setattr(s.objects["Box"], "location", (-1.0, 0.3, 0.6)),
    "vertex edited": lambda s: setattr(s.objects["Floor"].data.vertices[10].co, "z", 0.3),
    "modifier added": lambda s: s.objects["Box"].modifiers.new("Bevel", "BEVEL"),
    "modifier level": lambda s: setattr(s.objects["Smooth"].modifiers[0], "render_levels", 1)
    or setattr(s.objects["Smooth"].modifiers[0], "levels", 1),
    "shaded flat": lambda s: s.objects["Smooth"].data.shade_flat(),
    "terminator offset": lambda s: setattr(
        s.objects["Smooth"], "shadow_terminator_geometry_offset", 0.4),
    "hidden for render": lambda s: setattr(s.objects["Box"], "hide_render", True),
    "object added": lambda s: add_object(s, "Added", box_mesh("Added", 0.5), (0, 1, 0.25)),
}


@pytest.mark.parametrize("change", CHANGES)
def test_after_a_change_f12_sends_the_changed_scene(scene, monkeypatch, tmp_path,
                                                    change) -> None:
    """A flattened scene is made again after any change to what it is made of (and the
    change undone afterwards, so that the cases do not pile up)."""
    record = Record(monkeypatch)
    record.f12(scene, tmp_path / "before")
    CHANGES[change](scene)
    try:
        _, read, _ = record.f12(scene, tmp_path / "after")
        assert read >= 1  # the flattened scene is made again
        assert record.sent[-1] is not record.sent[0]
        assert_same_scene(record.sent[-1], fresh())
    finally:
        _restore(scene)


def _restore(scene: bpy.types.Scene) -> None:
    """The fixture's scene again."""
    box, smooth = scene.objects["Box"], scene.objects["Smooth"]
    box.location, box.hide_render = (-1.2, 0.0, 0.6), False
    for mod in list(box.modifiers):
        box.modifiers.remove(mod)
    scene.objects["Floor"].data.vertices[10].co.z = 0.0
    smooth.data.shade_smooth()
    smooth.modifiers[0].levels = smooth.modifiers[0].render_levels = 2
    smooth.shadow_terminator_geometry_offset = export.DEFAULT_TERMINATOR_OFFSET
    added = bpy.data.objects.get("Added")
    if added is not None:
        bpy.data.objects.remove(added)


def test_animated_geometry_is_read_again_on_another_frame(scene, monkeypatch,
                                                          tmp_path) -> None:
    """A Wave modifier moves the floor with time: a frame change is a geometry update."""
    record = Record(monkeypatch)
    floor = scene.objects["Floor"]
    wave = floor.modifiers.new("Wave", "WAVE")
    wave.height, wave.speed = 0.3, 0.5
    try:
        scene.frame_set(1)
        record.f12(scene, tmp_path / "frame1")
        scene.frame_set(5)
        _, read, _ = record.f12(scene, tmp_path / "frame5")
        assert read >= 1
        assert_same_scene(record.sent[-1], fresh())
        assert not np.array_equal(record.sent[-1].vertices, record.sent[0].vertices)
    finally:
        floor.modifiers.remove(wave)
        scene.frame_set(1)


def test_an_instance_list_reads_again_only_the_mesh_that_changed(scene, monkeypatch,
                                                                 tmp_path) -> None:
    group = bpy.data.collections.new("Group")
    group.objects.link(bpy.data.objects.new("Piece", box_mesh("Piece", 0.4)))
    holder = bpy.data.objects.new("Holder", None)
    holder.instance_type, holder.instance_collection = "COLLECTION", group
    holder.location = (0.0, 1.5, 0.2)
    scene.collection.objects.link(holder)
    record = Record(monkeypatch)
    try:
        _, read, _ = record.f12(scene, tmp_path / "first")
        assert isinstance(record.sent[-1], export.InstanceExport)
        assert read == 4
        holder.location.x += 0.5
        _, read, _ = record.f12(scene, tmp_path / "moved")
        assert read == 0
        assert not any(r.startswith("PUT /v1/meshes") for r in record.outcomes[-1].requests)
        scene.objects["Floor"].data.vertices[3].co.z = 0.2
        _, read, _ = record.f12(scene, tmp_path / "edited")
        assert read == 1
        puts = [r for r in record.outcomes[-1].requests if r.startswith("PUT /v1/meshes")]
        assert len(puts) == 1, record.outcomes[-1].requests
        listing = export.export_instances(bpy.context.evaluated_depsgraph_get())
        assert list(record.sent[-1].meshes) == list(listing.meshes)
        np.testing.assert_array_equal(record.sent[-1].transforms, listing.transforms)
    finally:
        scene.objects["Floor"].data.vertices[3].co.z = 0.0
        bpy.data.objects.remove(holder)
        bpy.data.objects.remove(bpy.data.objects["Piece"])
        bpy.data.collections.remove(group)


def test_without_persistent_data_nothing_is_kept(scene, monkeypatch, tmp_path) -> None:
    record = Record(monkeypatch)
    scene.render.use_persistent_data = False
    try:
        record.f12(scene, tmp_path / "first")
        _, read, hashed = record.f12(scene, tmp_path / "again")
        assert (read, hashed) == (3, 1)
        assert not persistent._kept
    finally:
        scene.render.use_persistent_data = True
