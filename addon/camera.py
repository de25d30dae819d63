"""The scene camera as a camera description and as primary rays (numpy only).

The same model as the engine's `kernels/camera.py` (Blender's conventions; see its
docstring and docs/addon.md): pixel centres, row 0 at the TOP of the image, float64
maths cast to float32, perspective clip planes as camera-space depths. The add-on
cannot import the engine, so the model is written again here and
tests/addon/test_camera.py checks that both give the same rays.
"""

from __future__ import annotations

from typing import Any

import bpy
import numpy as np


def resolution(scene: bpy.types.Scene) -> tuple[int, int]:
    """Final image size in pixels: resolution times the percentage, as Blender renders."""
    r = scene.render
    pct = r.resolution_percentage
    return max(1, int(r.resolution_x * pct / 100)), max(1, int(r.resolution_y * pct / 100))


def camera_dict(
    scene: bpy.types.Scene,
    depsgraph: bpy.types.Depsgraph | None = None,
    obj: bpy.types.Object | None = None,
) -> dict[str, Any]:
    """The camera description of the service's jobs API (`kernels.Camera.to_dict()` form)
    of `obj` (default: the scene's camera).

    With a depsgraph the evaluated camera is used (animation, constraints and moves
    made by a script just before). Raises ValueError, in words for the user, when the
    scene has no camera object.
    """
    obj = obj or scene.camera
    if obj is None or obj.type != "CAMERA":
        raise ValueError("The scene has no active camera: add one and make it active")
    if depsgraph is not None:
        obj = obj.evaluated_get(depsgraph)
    cam = obj.data
    if cam.type not in {"PERSP", "ORTHO"}:
        raise ValueError(
            f"Camera '{obj.name}' is {cam.type}; only Perspective and Orthographic work"
        )
    width, height = resolution(scene)
    return {
        "matrix_world": [list(map(float, row)) for row in obj.matrix_world],
        "width": width,
        "height": height,
        "type": cam.type,
        "lens": float(cam.lens),
        "sensor_width": float(cam.sensor_width),
        "sensor_height": float(cam.sensor_height),
        "sensor_fit": cam.sensor_fit,
        "ortho_scale": float(cam.ortho_scale),
        "shift_x": float(cam.shift_x),
        "shift_y": float(cam.shift_y),
        "clip_start": float(cam.clip_start),
        "clip_end": float(cam.clip_end),
    }


def window(scene: bpy.types.Scene) -> dict[str, int] | None:
    """The border's pixels as the jobs API's `window` (from the frame's top-left), None
    without a border. Blender's own rounding (render_init_from_main): float32 border
    times the final size, truncated; its y counts from the bottom."""
    r = scene.render
    if not r.use_border:
        return None
    w, h = resolution(scene)

    def edge(fraction: float, size: int) -> int:
        return int(np.float32(fraction) * np.float32(size))

    x0, x1 = edge(r.border_min_x, w), edge(r.border_max_x, w)
    y0, y1 = edge(r.border_min_y, h), edge(r.border_max_y, h)
    if x1 <= x0 or y1 <= y0:
        raise ValueError("The render border has no pixels: draw a larger one (Ctrl-B)")
    return {"x": x0, "y": h - y1, "width": x1 - x0, "height": y1 - y0}


def view(
    scene: bpy.types.Scene, depsgraph: bpy.types.Depsgraph, obj: bpy.types.Object | None = None
) -> dict[str, Any]:
    """What a render job sees: the camera, the border's window and the pixel aspect."""
    r = scene.render
    return {
        "camera": camera_dict(scene, depsgraph, obj),
        "window": window(scene),
        "pixel_aspect": [float(r.pixel_aspect_x), float(r.pixel_aspect_y)],
    }


def rays(cam: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One ray per pixel centre of a camera description, row-major, row 0 at the top.

    Returns origins (H*W,3), unit directions (H*W,3), tmin (H*W,) and tmax (H*W,),
    float32. Perspective rays start at the camera and carry the clip planes as ray
    parameters (`depth / cos`); orthographic rays start on the plane through the
    camera and use the clip distances as they are.
    """
    w, h = int(cam["width"]), int(cam["height"])
    m = np.asarray(cam["matrix_world"], dtype=np.float64)
    rot = m[:3, :3] / np.linalg.norm(m[:3, :3], axis=0)  # drop object scale, as Cycles does
    ortho = cam["type"] == "ORTHO"
    if ortho:
        s = float(cam["ortho_scale"])
    else:
        # AUTO takes sensor_width whichever side it fits (BKE_camera_sensor_size).
        sensor = cam["sensor_height"] if cam["sensor_fit"] == "VERTICAL" else cam["sensor_width"]
        s = float(sensor) / float(cam["lens"])
    fit = cam["sensor_fit"]
    horizontal = w >= h if fit == "AUTO" else fit == "HORIZONTAL"
    pix = s / (w if horizontal else h)

    rows, cols = np.divmod(np.arange(w * h, dtype=np.int64), w)
    pts = np.empty((w * h, 3), dtype=np.float64)
    pts[:, 0] = (cols + 0.5 - 0.5 * w) * pix + float(cam["shift_x"]) * s
    pts[:, 1] = (0.5 * h - (rows + 0.5)) * pix + float(cam["shift_y"]) * s
    pts[:, 2] = 0.0 if ortho else -1.0
    clip_start, clip_end = float(cam["clip_start"]), float(cam["clip_end"])
    if ortho:
        origins = m[:3, 3] + pts @ rot.T
        forward = -rot[:, 2] / np.linalg.norm(rot[:, 2])
        directions = np.broadcast_to(forward, origins.shape)
        tmin = np.full(w * h, clip_start)
        tmax = np.full(w * h, clip_end)
    else:
        world = pts @ rot.T
        length = np.linalg.norm(world, axis=1)  # the point at depth 1 lies at t = length
        directions = world / length[:, None]
        origins = np.broadcast_to(m[:3, 3], directions.shape)
        tmin = clip_start * length
        tmax = clip_end * length
    return (
        np.ascontiguousarray(origins, dtype=np.float32),
        np.ascontiguousarray(directions, dtype=np.float32),
        tmin.astype(np.float32),
        tmax.astype(np.float32),
    )


def ray_body(origins: np.ndarray, directions: np.ndarray) -> bytes:
    """The body of `POST /v1/scenes/{id}/ao`: R*6 little-endian float32 (origin, direction)."""
    packed = np.concatenate([origins, directions], axis=1)
    return np.ascontiguousarray(packed, dtype="<f4").tobytes()
