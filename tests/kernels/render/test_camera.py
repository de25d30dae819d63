"""Blender's camera model: analytic cases, validation, wire form, and real Blender (bpy)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scenesort.kernels import Camera

pytestmark = pytest.mark.host_only  # numpy and bpy

# --- helpers -----------------------------------------------------------------------


def rotation(axis: str, degrees: float) -> np.ndarray:
    """A 3x3 rotation about a coordinate axis."""
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    r = np.eye(3)
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


def placement(r: np.ndarray, t, scale=(1.0, 1.0, 1.0)) -> np.ndarray:
    """A 4x4 matrix_world from rotation, translation and per-axis object scale."""
    m = np.eye(4)
    m[:3, :3] = r * np.asarray(scale)
    m[:3, 3] = t
    return m


def camera_space(cam: Camera, world_dirs: np.ndarray) -> np.ndarray:
    """World directions expressed in the camera's (normalised) frame."""
    return world_dirs.astype(np.float64) @ cam.rotation


TILTED = placement(rotation("z", 30) @ rotation("x", 70), (1.0, -2.0, 3.0))


# --- analytic checks ---------------------------------------------------------------


def test_centre_ray_looks_along_local_minus_z() -> None:
    """With odd W and H the middle pixel's ray is the camera's -Z axis, from its origin."""
    cam = Camera(matrix_world=TILTED, width=5, height=3)
    o, d, _, _ = cam.rays()
    centre = 1 * 5 + 2
    np.testing.assert_allclose(o[centre], (1.0, -2.0, 3.0), atol=1e-6)
    np.testing.assert_allclose(d[centre], -TILTED[:3, 2], atol=1e-6)
    np.testing.assert_allclose(cam.forward, -TILTED[:3, 2], atol=1e-12)


def test_rays_shapes_dtypes_and_unit_length() -> None:
    cam = Camera(matrix_world=TILTED, width=7, height=4)
    o, d, tmin, tmax = cam.rays()
    assert o.shape == d.shape == (28, 3) and tmin.shape == tmax.shape == (28,)
    assert {a.dtype for a in (o, d, tmin, tmax)} == {np.dtype(np.float32)}
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-6)


def test_corner_rays_follow_vertical_field_of_view() -> None:
    """look_at keeps fov_y: the top-left pixel centre sits half a pixel inside the frustum."""
    w, h, fov = 8, 6, 60.0
    cam = Camera.look_at((0, 0, 0), (0, 0, -1), (0, 1, 0), fov, w, h)
    _, d, _, _ = cam.rays()
    half = math.tan(math.radians(fov / 2))
    pix = 2 * half / h
    expect_tl = np.array([-(w / 2 - 0.5) * pix, (h / 2 - 0.5) * pix, -1.0])
    expect_br = np.array([(w / 2 - 0.5) * pix, -(h / 2 - 0.5) * pix, -1.0])
    np.testing.assert_allclose(d[0], expect_tl / np.linalg.norm(expect_tl), atol=1e-6)
    np.testing.assert_allclose(d[-1], expect_br / np.linalg.norm(expect_br), atol=1e-6)
    # The frame's edge (not a pixel centre) is exactly at fov_y / 2.
    edge = cam.raster_to_camera(np.array([w / 2]), np.array([0.0]))[0]
    assert math.degrees(math.atan2(edge[1], -edge[2])) == pytest.approx(fov / 2, abs=1e-9)


def test_look_at_camera_points_at_target_with_up_kept_upright() -> None:
    cam = Camera.look_at((3, 4, 5), (0, 1, 0), (0, 1, 0), 35, 64, 48)
    fwd = np.array([-3.0, -3.0, -5.0]) / math.sqrt(43)
    np.testing.assert_allclose(cam.forward, fwd, atol=1e-12)
    assert cam.rotation[1, 1] > 0  # camera +Y has a positive world-Y component
    assert abs(cam.rotation[:, 0] @ np.array([0.0, 1.0, 0.0])) < 1e-12  # no roll


def test_row_zero_is_the_top_of_the_image() -> None:
    """Ray i is pixel (i // W, i % W); rows go down, columns go right."""
    cam = Camera(matrix_world=np.eye(4), width=4, height=3)
    _, d, _, _ = cam.rays()
    grid = d.reshape(3, 4, 3)
    assert np.all(grid[0, :, 1] > 0) and np.all(grid[-1, :, 1] < 0)
    assert np.all(np.diff(grid[:, 0, 1]) < 0)
    assert np.all(np.diff(grid[0, :, 0]) > 0)


def test_shift_moves_the_frame_by_fraction_of_fitted_side() -> None:
    base = Camera(matrix_world=np.eye(4), width=5, height=3, lens=40.0)
    shifted = Camera(
        matrix_world=np.eye(4), width=5, height=3, lens=40.0, shift_x=0.25, shift_y=-0.1
    )
    s = 36.0 / 40.0  # AUTO, landscape: sensor_width across x
    p0 = base.raster_to_camera(np.array([2.5]), np.array([1.5]))[0]
    p1 = shifted.raster_to_camera(np.array([2.5]), np.array([1.5]))[0]
    np.testing.assert_allclose(p1 - p0, (0.25 * s, -0.1 * s, 0.0), atol=1e-12)
    _, d, _, _ = shifted.rays()
    np.testing.assert_allclose(
        d[7], np.array([0.25 * s, -0.1 * s, -1]) / math.hypot(0.25 * s, 0.1 * s, 1), atol=1e-6
    )


def test_ortho_rays_are_parallel_and_evenly_spaced() -> None:
    cam = Camera(
        matrix_world=TILTED,
        width=6,
        height=4,
        type="ORTHO",
        ortho_scale=3.0,
        clip_start=0.5,
        clip_end=20.0,
    )
    o, d, tmin, tmax = cam.rays()
    np.testing.assert_allclose(d, np.broadcast_to(cam.forward, d.shape), atol=1e-6)
    local = camera_space(cam, o - cam.position)
    grid = local.reshape(4, 6, 3)
    np.testing.assert_allclose(np.diff(grid[..., 0], axis=1), 3.0 / 6, atol=1e-6)
    np.testing.assert_allclose(np.diff(grid[..., 1], axis=0), -3.0 / 6, atol=1e-6)
    np.testing.assert_allclose(local[:, 2], 0.0, atol=1e-6)  # on the plane through the camera
    np.testing.assert_allclose(grid[0, 0, :2], (-1.25, 0.75), atol=1e-6)
    assert np.all(tmin == np.float32(0.5)) and np.all(tmax == np.float32(20.0))


@pytest.mark.parametrize(("w", "h"), [(40, 30), (30, 40), (32, 32)])
def test_auto_fit_spreads_sensor_width_over_the_longer_side(w: int, h: int) -> None:
    """AUTO uses sensor_width across the wider side, in portrait too (never sensor_height)."""
    cam = Camera(matrix_world=np.eye(4), width=w, height=h, lens=25.0, sensor_height=99.0)
    left, top = cam.raster_to_camera(np.array([0.0, w / 2]), np.array([h / 2, 0.0]))
    half_extent = (-left[0]) if w >= h else top[1]
    assert half_extent == pytest.approx(0.5 * 36.0 / 25.0)


def test_fixed_fits_use_their_own_sensor_side() -> None:
    hor = Camera(matrix_world=np.eye(4), width=30, height=40, lens=20.0, sensor_fit="HORIZONTAL")
    ver = Camera(matrix_world=np.eye(4), width=40, height=30, lens=20.0, sensor_fit="VERTICAL")
    assert -hor.raster_to_camera([0.0], [20.0])[0, 0] == pytest.approx(18.0 / 20.0)
    assert ver.raster_to_camera([20.0], [0.0])[0, 1] == pytest.approx(12.0 / 20.0)


def test_perspective_clip_range_is_camera_space_depth() -> None:
    cam = Camera(matrix_world=TILTED, width=9, height=7, lens=18.0, clip_start=0.25, clip_end=7.5)
    o, d, tmin, tmax = cam.rays()
    depth_near = tmin * (d.astype(np.float64) @ cam.forward)
    depth_far = tmax * (d.astype(np.float64) @ cam.forward)
    np.testing.assert_allclose(depth_near, 0.25, rtol=1e-6)
    np.testing.assert_allclose(depth_far, 7.5, rtol=1e-6)
    assert tmin.max() > tmin.min() * 1.1  # corner rays start further along than the centre


def test_object_scale_is_removed_before_use() -> None:
    """Blender normalises the camera's axes: a scaled camera casts the same rays."""
    plain = Camera(matrix_world=TILTED, width=6, height=5)
    scaled = Camera(
        matrix_world=placement(TILTED[:3, :3], TILTED[:3, 3], (2.0, 0.5, 3.0)), width=6, height=5
    )
    for a, b in zip(plain.rays(), scaled.rays(), strict=True):
        np.testing.assert_allclose(a, b, atol=1e-6)


# --- validation and wire form --------------------------------------------------------


@pytest.mark.parametrize(
    ("changes", "field_name"),
    [
        ({"width": 0}, "width"),
        ({"height": 2.5}, "height"),
        ({"width": True}, "width"),
        ({"type": "PANO"}, "type"),
        ({"sensor_fit": "FILL"}, "sensor_fit"),
        ({"lens": 0.0}, "lens"),
        ({"sensor_width": -1.0}, "sensor_width"),
        ({"ortho_scale": math.nan}, "ortho_scale"),
        ({"shift_x": math.inf}, "shift_x"),
        ({"clip_start": -0.1}, "clip_start"),
        ({"clip_start": 5.0, "clip_end": 5.0}, "clip_end"),
        ({"aperture_size": -0.1}, "aperture_size"),
        ({"focus_distance": 0.0}, "focus_distance"),
        ({"aperture_blades": 2}, "aperture_blades"),
        ({"aperture_blades": 17}, "aperture_blades"),
        ({"aperture_ratio": 0.0}, "aperture_ratio"),
        ({"aperture_rotation": math.nan}, "aperture_rotation"),
        ({"matrix_world": np.eye(3)}, "matrix_world"),
        ({"matrix_world": np.diag([1.0, 0.0, 1.0, 1.0])}, "matrix_world"),
        ({"matrix_world": np.full((4, 4), np.nan)}, "matrix_world"),
        (
            {"matrix_world": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]},
            "matrix_world",
        ),
    ],
)
def test_bad_fields_raise_value_error_naming_the_field(changes: dict, field_name: str) -> None:
    kwargs = {"matrix_world": np.eye(4), "width": 4, "height": 3} | changes
    with pytest.raises(ValueError, match=f"camera.{field_name}"):
        Camera(**kwargs)


def test_look_at_rejects_degenerate_input() -> None:
    with pytest.raises(ValueError, match="parallel"):
        Camera.look_at((0, 0, 0), (0, 1, 0), (0, 1, 0), 40, 4, 4)
    with pytest.raises(ValueError, match="differ"):
        Camera.look_at((1, 1, 1), (1, 1, 1), (0, 1, 0), 40, 4, 4)
    with pytest.raises(ValueError, match="fov_y_deg"):
        Camera.look_at((0, 0, 1), (0, 0, 0), (0, 1, 0), 180, 4, 4)


def test_wire_form_round_trips_through_json() -> None:
    cam = Camera(
        matrix_world=TILTED,
        width=33,
        height=21,
        type="ORTHO",
        ortho_scale=2.5,
        shift_x=0.1,
        sensor_fit="VERTICAL",
        clip_start=0.01,
        clip_end=50.0,
    )
    again = Camera.from_dict(json.loads(json.dumps(cam.to_dict())))
    assert again == cam
    for a, b in zip(cam.rays(), again.rays(), strict=True):
        np.testing.assert_array_equal(a, b)


def test_from_dict_lists_valid_keys_for_unknown_ones() -> None:
    data = Camera(matrix_world=np.eye(4), width=4, height=3).to_dict() | {"fov": 40}
    with pytest.raises(ValueError, match=r"unknown keys \['fov'\].*valid keys.*sensor_fit"):
        Camera.from_dict(data)
    with pytest.raises(ValueError, match=r"missing required keys \['height'\]"):
        Camera.from_dict({"matrix_world": np.eye(4).tolist(), "width": 4})
    with pytest.raises(ValueError, match="JSON object"):
        Camera.from_dict([1, 2])  # type: ignore[arg-type]


# --- against real Blender ------------------------------------------------------------

BLENDER_CASES = {
    "landscape": {"width": 64, "height": 36, "lens": 35.0},
    "portrait_auto": {"width": 30, "height": 50, "lens": 28.0, "shift_y": 0.12},
    "square_shift": {"width": 40, "height": 40, "shift_x": -0.2, "shift_y": 0.15},
    "vertical_fit": {"width": 48, "height": 20, "sensor_fit": "VERTICAL", "sensor_height": 18.0},
    "horizontal_fit_portrait": {
        "width": 20,
        "height": 44,
        "sensor_fit": "HORIZONTAL",
        "lens": 70.0,
        "sensor_width": 24.0,
        "shift_x": 0.05,
    },
    "ortho": {"width": 50, "height": 30, "type": "ORTHO", "ortho_scale": 4.5, "shift_x": 0.1},
    "ortho_portrait": {
        "width": 24,
        "height": 40,
        "type": "ORTHO",
        "ortho_scale": 2.0,
        "sensor_fit": "AUTO",
        "shift_y": -0.2,
    },
}


@pytest.fixture(scope="module")
def bpy_module():
    import bpy  # a dev dependency: an ImportError here means a broken install, not a skip

    bpy.ops.wm.read_factory_settings(use_empty=True)
    return bpy


def blender_camera(bpy, cam: Camera):
    """A bpy scene camera with exactly `cam`'s settings (fresh empty scene)."""
    from mathutils import Matrix

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    data = bpy.data.cameras.new("cam")
    for name in (
        "type",
        "lens",
        "sensor_width",
        "sensor_height",
        "sensor_fit",
        "ortho_scale",
        "shift_x",
        "shift_y",
        "clip_start",
        "clip_end",
    ):
        setattr(data, name, getattr(cam, name))
    obj = bpy.data.objects.new("cam", data)
    scene.collection.objects.link(obj)
    # A nested list assigned to the property is read column by column; Matrix() takes rows.
    obj.matrix_world = Matrix([list(row) for row in cam.matrix_world])
    scene.camera = obj
    scene.render.resolution_x, scene.render.resolution_y = cam.width, cam.height
    scene.render.resolution_percentage = 100
    bpy.context.view_layer.update()
    # Reading back row by row gives the wire form: what the add-on should send.
    rows = np.array([tuple(row) for row in obj.matrix_world])
    np.testing.assert_allclose(rows, cam.matrix_world, atol=1e-6)
    return scene, obj


def make_case(name: str) -> Camera:
    # A scaled, rotated, translated camera: Blender must drop the scale as we do.
    m = placement(rotation("y", -25) @ rotation("x", 15), (0.5, -1.0, 2.0), (1.5, 1.5, 1.5))
    return Camera(matrix_world=m, clip_start=0.05, clip_end=100.0, **BLENDER_CASES[name])


@pytest.mark.parametrize("case", sorted(BLENDER_CASES))
def test_frame_corners_match_blender_view_frame(bpy_module, case: str) -> None:
    """Our image-plane corners equal `Camera.view_frame(scene=...)` in camera space."""
    cam = make_case(case)
    scene, obj = blender_camera(bpy_module, cam)
    frame = np.array([tuple(v) for v in obj.data.view_frame(scene=scene)])
    # view_frame order: top-right, bottom-right, bottom-left, top-left.
    ours = cam.raster_to_camera(
        np.array([cam.width, cam.width, 0, 0]), np.array([0, cam.height, cam.height, 0])
    )
    if cam.type == "PERSP":
        frame = frame / -frame[:, 2:3]  # view_frame draws at its own depth; compare at 1
    np.testing.assert_allclose(frame[:, :2], ours[:, :2], rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("case", sorted(BLENDER_CASES))
def test_every_pixel_projects_back_to_its_centre_in_blender(bpy_module, case: str) -> None:
    """Points along each ray land on that pixel's centre in `world_to_camera_view`.

    Blender's normalised view coordinates have y = 0 at the bottom row, so pixel
    (r, c) must map to ((c + 0.5) / W, 1 - (r + 0.5) / H), in front of the camera.
    """
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector

    cam = make_case(case)
    scene, obj = blender_camera(bpy_module, cam)
    o, d, tmin, tmax = cam.rays()
    rows, cols = np.divmod(np.arange(cam.width * cam.height), cam.width)
    expect = np.stack([(cols + 0.5) / cam.width, 1 - (rows + 0.5) / cam.height], axis=1)
    t = tmin.astype(np.float64) + 3.0
    points = o.astype(np.float64) + t[:, None] * d.astype(np.float64)
    got = np.array([tuple(world_to_camera_view(scene, obj, Vector(p))) for p in points])
    np.testing.assert_allclose(got[:, :2], expect, atol=2e-5)
    # Its z is camera-space depth: clip_start + 3 * cos for PERSP, 3 + clip_start for ORTHO.
    depth = t * (d.astype(np.float64) @ cam.forward)
    np.testing.assert_allclose(got[:, 2], depth, rtol=1e-5)
    assert np.all(np.isfinite(tmax))
