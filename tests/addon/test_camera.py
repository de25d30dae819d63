"""The add-on's camera description, rendered by the engine's camera model, matches
Blender's own camera frame; the border's window follows Blender's rounding."""

from __future__ import annotations

import math

import bpy
import numpy as np
import pytest
from blender_scenes import add_camera, add_object

from addon import camera


def _rays(desc: dict) -> tuple[np.ndarray, ...]:
    """The service's rays for a camera description (the engine's model)."""
    from scenesort.kernels import Camera

    return Camera.from_dict(desc).rays()


# (name, settings of the camera data, resolution x, y, percentage, object scale)
CAMERAS = [
    ("landscape", {}, 64, 48, 100, (1, 1, 1)),
    ("portrait_auto", {"lens": 35.0}, 30, 50, 100, (1, 1, 1)),
    ("horizontal_shift", {"sensor_fit": "HORIZONTAL", "shift_x": 0.2, "shift_y": -0.1}, 40, 40, 100, (1, 1, 1)),  # noqa: E501
    ("vertical_shift", {"sensor_fit": "VERTICAL", "shift_x": -0.15, "shift_y": 0.05, "sensor_height": 18.0}, 80, 30, 100, (1, 1, 1)),  # noqa: E501
    # An even size: view_frame uses the full-size aspect, a render the truncated pixels.
    ("half_resolution_scaled", {"clip_start": 0.5, "clip_end": 40.0}, 102, 68, 50, (2, 3, 0.5)),
    ("ortho", {"type": "ORTHO", "ortho_scale": 7.5, "shift_x": 0.1}, 48, 32, 100, (1, 1, 1)),
    ("ortho_vertical", {"type": "ORTHO", "sensor_fit": "VERTICAL", "ortho_scale": 3.0}, 20, 50, 100, (1, 1, 1)),  # noqa: E501
]  # fmt: skip


def _setup(
    scene: bpy.types.Scene, settings: dict, w: int, h: int, pct: int, scale
) -> bpy.types.Object:
    cam = add_camera(scene, (1.0, -6.0, 2.5), (math.radians(75), 0.3, math.radians(10)), w, h)
    scene.render.resolution_percentage = pct
    cam.scale = scale
    for key, value in settings.items():
        setattr(cam.data, key, value)
    bpy.context.view_layer.update()
    return cam


@pytest.mark.parametrize("name,settings,w,h,pct,scale", CAMERAS, ids=[c[0] for c in CAMERAS])
def test_description_is_the_engines_wire_form(registered, name, settings, w, h, pct, scale) -> None:
    from scenesort.kernels import Camera

    _setup(registered, settings, w, h, pct, scale)
    desc = camera.camera_dict(registered)
    assert (desc["width"], desc["height"]) == (w * pct // 100, h * pct // 100)
    assert Camera.from_dict(desc).to_dict().items() >= desc.items()  # valid, nothing lost


@pytest.mark.parametrize("name,settings,w,h,pct,scale", CAMERAS, ids=[c[0] for c in CAMERAS])
def test_image_corners_match_blenders_view_frame(
    registered, name, settings, w, h, pct, scale
) -> None:
    """Independent of both models: Blender's `Camera.view_frame` gives the image corners."""
    cam = _setup(registered, settings, w, h, pct, scale)
    desc = camera.camera_dict(registered)
    width, height = desc["width"], desc["height"]
    origins, directions, _, _ = _rays(desc)
    m = np.asarray(desc["matrix_world"])
    rot = m[:3, :3] / np.linalg.norm(m[:3, :3], axis=0)

    def plane_point(i: int) -> np.ndarray:
        """Pixel i's centre on the camera's image plane (depth 1, or the ortho plane)."""
        if cam.data.type == "ORTHO":
            return rot.T @ (origins[i].astype(np.float64) - m[:3, 3])
        local = rot.T @ directions[i].astype(np.float64)
        return local / -local[2]

    top_left = plane_point(0)
    bottom_right = plane_point(width * height - 1)
    pix = (plane_point(1) - top_left)[0] if width > 1 else None
    assert pix is not None and pix > 0
    # Pixel centres sit half a pixel inside the frame's corners.
    top_left_corner = top_left[:2] + [-pix / 2, pix / 2]
    bottom_right_corner = bottom_right[:2] + [pix / 2, -pix / 2]
    frame = np.array([tuple(v) for v in cam.data.view_frame(scene=registered)])
    # view_frame: top-right, bottom-right, bottom-left, top-left (PERSP at some depth).
    if cam.data.type == "PERSP":
        frame = frame / -frame[:, 2:3]
    np.testing.assert_allclose(top_left_corner, frame[3, :2], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(bottom_right_corner, frame[1, :2], rtol=1e-5, atol=1e-5)


def test_row_zero_is_the_top_of_the_image(registered) -> None:
    add_camera(registered, (0.0, 0.0, 5.0), (0.0, 0.0, 0.0), 8, 6)  # looks down -Z, +Y up
    depsgraph = bpy.context.evaluated_depsgraph_get()  # places the camera just moved
    origins, directions, _, _ = _rays(camera.camera_dict(registered, depsgraph))
    grid = directions.reshape(6, 8, 3)
    assert grid[0, 0, 1] > 0 > grid[-1, 0, 1]  # first row points up (+Y), last row down
    assert grid[0, 0, 0] < 0 < grid[0, -1, 0]  # first column left, last column right
    np.testing.assert_array_equal(origins, np.tile([0.0, 0.0, 5.0], (48, 1)).astype(np.float32))


def test_odd_percentage_truncates_like_blender(registered) -> None:
    add_camera(registered, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 101, 67)
    registered.render.resolution_percentage = 50
    assert camera.resolution(registered) == (50, 33)


def test_perspective_clip_range_is_depth(registered) -> None:
    cam = add_camera(registered, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 16, 16)
    cam.data.clip_start, cam.data.clip_end = 2.0, 10.0
    _, directions, tmin, tmax = _rays(camera.camera_dict(registered))
    depth_per_t = -directions[:, 2]  # camera looks down -Z
    np.testing.assert_allclose(tmin * depth_per_t, 2.0, rtol=1e-6)
    np.testing.assert_allclose(tmax * depth_per_t, 10.0, rtol=1e-6)


def test_no_camera_is_a_clear_error(registered) -> None:
    with pytest.raises(ValueError, match="no active camera"):
        camera.camera_dict(registered)
    add_object(registered, "Empty", None)
    registered.camera = bpy.data.objects["Empty"]
    with pytest.raises(ValueError, match="no active camera"):
        camera.camera_dict(registered)


def test_border_window_uses_blenders_rounding(registered) -> None:
    """float32 border times the final size, truncated; y counted from the bottom."""
    add_camera(registered, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 101, 67)
    r = registered.render
    assert camera.window(registered) is None
    r.use_border = True
    r.border_min_x, r.border_max_x, r.border_min_y, r.border_max_y = 0.1, 0.7, 0.25, 0.9
    x0, x1 = int(np.float32(0.1) * 101), int(np.float32(0.7) * 101)
    y0, y1 = int(np.float32(0.25) * 67), int(np.float32(0.9) * 67)
    assert (x0, x1, y0, y1) == (10, 70, 16, 60)
    assert camera.window(registered) == {"x": 10, "y": 67 - 60, "width": 60, "height": 44}
    r.border_max_x = r.border_min_x
    with pytest.raises(ValueError, match="border has no pixels"):
        camera.window(registered)
    r.use_border, r.pixel_aspect_x = False, 2.0
    view = camera.view(registered, bpy.context.evaluated_depsgraph_get())
    assert view["window"] is None and view["pixel_aspect"] == [2.0, 1.0]
