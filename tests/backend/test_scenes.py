"""Scene loading (real shared meshes) and the built-in default scene."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import warp as wp
from scenesort.backend.render import scenes
from scenesort.backend.render.scenes import (
    Scene,
    default_scene,
    load_mesh,
    shared_scene,
    shared_scenes_dir,
)
from scenesort.kernels import Camera

SHARED = shared_scenes_dir()
INFOS = scenes.shared_scene_infos()


@wp.kernel
def _closest_hit(
    mesh: wp.uint64,
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    t_out: wp.array(dtype=float),
):
    i = wp.tid()
    q = wp.mesh_query_ray(mesh, origins[i], directions[i], 1.0e30)
    t_out[i] = wp.where(q.result, q.t, -1.0)


def trace_with_warp_mesh(scene: Scene, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Closest-hit distance per ray with Warp's own BVH (an independent tracer); -1 = miss."""
    mesh = wp.Mesh(
        points=wp.array(scene.vertices, dtype=wp.vec3, device="cpu"),
        indices=wp.array(scene.indices.ravel(), dtype=wp.int32, device="cpu"),
    )
    t = wp.zeros(len(origins), dtype=float, device="cpu")
    wp.launch(
        _closest_hit,
        dim=len(origins),
        inputs=[mesh.id, wp.array(origins, dtype=wp.vec3), wp.array(directions, dtype=wp.vec3)],
        outputs=[t],
        device="cpu",
    )
    return t.numpy()


def project(camera: Camera, points: np.ndarray) -> np.ndarray:
    """Raster coordinates (px from the left, py from the top) of world points, PERSP only."""
    local = (points - camera.position) @ camera.rotation
    depth = -local[:, 2]
    edge = camera.raster_to_camera(np.array([0.0]), np.array([0.0]))[0]  # top-left corner
    pix = 2 * edge[1] / camera.height
    px = local[:, 0] / depth / pix + camera.width / 2
    py = camera.height / 2 - local[:, 1] / depth / pix
    return np.stack([px, py, depth], axis=1)


# --- shared scenes ----------------------------------------------------------------------


def test_shared_scenes_folder_is_found() -> None:
    """This checkout sits beside ../shared; a fresh clone gets None instead."""
    assert SHARED is not None and (SHARED / "scenes.json").is_file()
    assert len(INFOS) == 7


@pytest.mark.parametrize("name", sorted(INFOS))
def test_shared_scene_loads_every_face_with_its_camera(name: str) -> None:
    info = INFOS[name]
    scene = shared_scene(name, width=64, height=48)
    assert scene.name == name
    assert scene.vertices.dtype == np.float32 and scene.vertices.shape == (info["vertices"], 3)
    # Duplicated and zero-area faces are kept (Blender's importer would drop them).
    assert scene.indices.dtype == np.int32 and scene.triangles == info["triangles"]
    assert scene.indices.min() >= 0 and scene.indices.max() < len(scene.vertices)
    np.testing.assert_allclose(scene.vertices.min(0), info["bounds"]["min"], rtol=1e-3, atol=1e-4)
    np.testing.assert_allclose(scene.vertices.max(0), info["bounds"]["max"], rtol=1e-3, atol=1e-4)
    cam = info["camera"]
    np.testing.assert_allclose(scene.camera.position, cam["position"])
    look = np.subtract(cam["look_at"], cam["position"])
    np.testing.assert_allclose(scene.camera.forward, look / np.linalg.norm(look), atol=1e-12)
    assert (scene.camera.width, scene.camera.height) == (64, 48)


def test_buddha_keeps_duplicated_faces() -> None:
    _, indices = load_mesh(SHARED / "buddha.ply")
    unique = np.unique(np.sort(indices, axis=1), axis=0)
    assert len(indices) - len(unique) == 24  # scenes/README.md: 24 duplicated faces


def test_sponza_camera_sees_the_atrium() -> None:
    """scenes/README.md: 97.8% of the sponza camera's pixels hit (at 256x256)."""
    scene = shared_scene("sponza", width=64, height=64)
    o, d, _, _ = scene.camera.rays()
    hit = trace_with_warp_mesh(scene, o, d) > 0
    assert 0.93 < hit.mean() < 1.0


def test_unknown_scene_names_the_valid_ones() -> None:
    with pytest.raises(ValueError, match=r"unknown scene 'teapot'.*'bunny'"):
        shared_scene("teapot")


def test_env_override_must_point_at_a_scenes_folder(monkeypatch, tmp_path: Path) -> None:
    monkeypatch.setenv(scenes.SCENES_ENV, str(tmp_path))
    with pytest.raises(ValueError, match="SCENESORT_SCENES"):
        shared_scenes_dir()
    (tmp_path / "scenes.json").write_text(json.dumps([]))
    assert shared_scenes_dir() == tmp_path
    assert scenes.shared_scene_infos() == {}


def test_load_mesh_reports_bad_files(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="is not a file"):
        load_mesh(tmp_path / "missing.ply")
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nend_header\n")
    with pytest.raises(ValueError, match="bad.ply"):
        load_mesh(bad)


def test_load_mesh_reads_a_small_obj_as_written(tmp_path: Path) -> None:
    """Two identical faces and a zero-area one survive; indices keep their order."""
    path = tmp_path / "tri.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 2 0 0\nf 1 2 3\nf 1 2 3\nf 1 2 4\n")
    v, t = load_mesh(path)
    assert v.dtype == np.float32 and t.dtype == np.int32
    np.testing.assert_array_equal(t, [[0, 1, 2], [0, 1, 2], [0, 1, 3]])


# --- the default scene --------------------------------------------------------------------


@pytest.fixture(scope="module")
def default() -> Scene:
    return default_scene(width=160, height=120)


def test_default_scene_is_deterministic(default: Scene) -> None:
    again = default_scene(width=160, height=120)
    np.testing.assert_array_equal(default.vertices, again.vertices)
    np.testing.assert_array_equal(default.indices, again.indices)
    assert default.camera == again.camera


def test_default_scene_size_and_ranges(default: Scene) -> None:
    v, t = default.vertices, default.indices
    assert v.dtype == np.float32 and t.dtype == np.int32
    assert 50_000 <= len(t) <= 150_000
    assert np.all(np.isfinite(v))
    assert t.min() == 0 and t.max() == len(v) - 1  # every vertex used, none out of range
    np.testing.assert_array_equal(v.min(0), (-5, -9, 0))  # the room: floor at z = 0
    np.testing.assert_array_equal(v.max(0), (9, 5, 5))
    e1, e2 = v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]
    assert np.linalg.norm(np.cross(e1, e2), axis=1).min() > 0  # no degenerate triangles


def test_default_camera_centre_ray_hits_geometry(default: Scene) -> None:
    o, d, _, _ = default.camera.rays()
    centre = (default.camera.height // 2) * default.camera.width + default.camera.width // 2
    t = trace_with_warp_mesh(default, o[centre : centre + 1], d[centre : centre + 1])
    assert 0 < t[0] < 20


def test_default_camera_sees_every_object_and_the_room_corner(default: Scene) -> None:
    """Objects (everything above the floor away from the walls) project inside the frame,
    and the room's corners, where AO is darkest, are visible rather than hidden."""
    v = default.vertices.astype(np.float64)
    objects = v[(v[:, 2] > 1e-6) & (v[:, 0] > -4.999) & (v[:, 1] < 4.999)]
    p = project(default.camera, objects)
    assert np.all(p[:, 2] > 0)
    assert np.all((p[:, 0] > 0) & (p[:, 0] < 160) & (p[:, 1] > 0) & (p[:, 1] < 120))
    # Where the walls meet above the corner box, and where the left wall meets the floor.
    corners = np.array([[-5.0, 5.0, 3.0], [-5.0, 0.0, 0.0]])
    p = project(default.camera, corners)
    assert np.all((p[:, 0] > 0) & (p[:, 0] < 160) & (p[:, 1] > 0) & (p[:, 1] < 120))
    direction = corners - default.camera.position
    dist = np.linalg.norm(direction, axis=1)
    t = trace_with_warp_mesh(
        default,
        np.tile(default.camera.position, (2, 1)).astype(np.float32),
        (direction / dist[:, None]).astype(np.float32),
    )
    np.testing.assert_allclose(t, dist, rtol=1e-3)  # nothing stands in front of them


def test_default_camera_hits_mostly_geometry(default: Scene) -> None:
    o, d, _, _ = default.camera.rays()
    hit = trace_with_warp_mesh(default, o, d) > 0
    assert hit.mean() > 0.9  # a room: sky only above the walls
