"""File > Export > scenesort animation in real bpy, read back with backend/render/bundle.py: the
same meshes, transforms and cameras as Blender has at each frame, instanced meshes once,
a deformed mesh only in the frames where it changed, and the user's frame set back."""

from __future__ import annotations

from pathlib import Path

import bpy
import numpy as np
import pytest
from blender_scenes import FRAMES, add_object, animated_scene, box_mesh
from scenesort.backend.render.bundle import BundleError, read_bundle

from addon import animation, camera, export


@pytest.fixture
def animated(registered: bpy.types.Scene) -> bpy.types.Scene:
    return animated_scene(registered)


def _flatten(bundle, frame) -> tuple[np.ndarray, np.ndarray]:  # noqa: ANN001
    """The frame's instances as one world-space triangle list (float64 transform)."""
    listing = frame.instances
    vertices, triangles, start = [], [], 0
    for mesh_index, transform in zip(listing.mesh_index, listing.transforms, strict=True):
        mesh = bundle.mesh(listing.mesh_ids[mesh_index])
        m = transform.astype(np.float64)
        vertices.append((mesh.vertices @ m[:, :3].T + m[:, 3]).astype(np.float32))
        triangles.append(mesh.indices + start)
        start += len(mesh.vertices)
    return np.concatenate(vertices), np.concatenate(triangles)


def test_bundle_holds_what_blender_renders_at_each_frame(animated, tmp_path: Path) -> None:
    """Per frame, the bundle's instances flattened are `export_scene`'s triangles (the
    flattened scene the engine sends for F12), and its camera is `camera.view`'s."""
    scene = animated
    assert bpy.ops.scenesort.export_animation(directory=str(tmp_path)) == {"FINISHED"}
    assert scene.frame_current == 2  # the user's frame, set back
    bundle = read_bundle(tmp_path)
    assert bundle.frames == FRAMES
    assert bundle.settings == {"spp": 4, "seed": 3, "method": "sah", "leaf_size": 8,
                               "distance": 1.5, "pixel_filter": "BLACKMAN_HARRIS",
                               "filter_width": 1.5}  # the scene's film: Cycles' defaults
    for number in FRAMES:
        frame = bundle.frame(number)
        scene.frame_set(number)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        flat = export.export_scene(depsgraph)
        vertices, triangles = _flatten(bundle, frame)
        np.testing.assert_array_equal(vertices, flat.vertices)
        # export_scene reverses the winding of mirrored instances: compare as vertex sets
        np.testing.assert_array_equal(np.sort(triangles, axis=1),
                                      np.sort(flat.indices, axis=1))
        view = camera.view(scene, depsgraph)
        assert frame.request.camera.model_dump(exclude_unset=True) == view["camera"]  # exact
        assert frame.request.window is None and list(frame.request.pixel_aspect) == [1, 1]
        assert frame.instances.transforms.shape == (6, 3, 4)  # floor, 3 cubes, blob, part


def test_meshes_are_written_once_and_deformed_ones_where_they_change(animated,
                                                                      tmp_path: Path) -> None:
    """The cube (four instances) and the floor are one file each for all frames; the blob
    is a new mesh of the same topology in frames 1-3 and the same as frame 3's on frame 4."""
    assert bpy.ops.scenesort.export_animation(directory=str(tmp_path)) == {"FINISHED"}
    bundle = read_bundle(tmp_path)
    per_frame = [bundle.frame(f).instances for f in FRAMES]
    cube = {listing.mesh_ids[listing.mesh_index[1]] for listing in per_frame}
    assert len(cube) == 1  # Cube0's mesh in every frame
    assert all(listing.mesh_ids[listing.mesh_index[5]] in cube for listing in per_frame)
    blob = [listing.mesh_ids[listing.mesh_index[4]] for listing in per_frame]
    assert len(set(blob[:3])) == 3 and blob[3] == blob[2]
    assert len({bundle.mesh(b).topology for b in blob}) == 1
    assert len(bundle.mesh_info) == 2 + 3  # floor, cube, three blob shapes
    assert sorted(p.stem for p in (tmp_path / "meshes").iterdir()) == sorted(bundle.mesh_info)
    moved = [listing.transforms[2] for listing in per_frame]  # Cube1 rises until frame 3
    assert not np.array_equal(moved[0], moved[1]) and np.array_equal(moved[2], moved[3])


def test_export_failure_changes_nothing(registered, tmp_path: Path) -> None:
    """Without a camera the export is refused in words, no manifest is written, and the
    current frame is the user's."""
    scene = registered
    add_object(scene, "Box", box_mesh("Box"))
    scene.frame_start, scene.frame_end = 1, 5
    scene.frame_set(4)
    with pytest.raises(RuntimeError, match="no active camera"):
        bpy.ops.scenesort.export_animation(directory=str(tmp_path))
    assert scene.frame_current == 4
    assert not (tmp_path / "manifest.json").exists()
    with pytest.raises(BundleError, match="manifest.json"):
        read_bundle(tmp_path)


def test_export_is_in_the_file_export_menu(registered) -> None:
    assert animation._menu in bpy.types.TOPBAR_MT_file_export._dyn_ui_initialize()
    assert bpy.ops.scenesort.export_animation.poll()
