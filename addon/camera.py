"""The scene camera and film as a render job's view: the camera description of the
service's jobs API (`kernels/render/camera.py`'s wire form, Blender's camera model), the
border's window and the pixel aspect. The service makes the rays;
tests/addon/test_camera.py checks its model against Blender's own camera frame.
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
        **depth_of_field(obj),
    }


def depth_of_field(obj: bpy.types.Object) -> dict[str, Any]:
    """The camera's depth of field as Cycles takes it (blender/camera.cpp): the lens's
    radius in world units, lens * 1e-3 / (2 * f-stop) (1 / (2 * f-stop) for an
    orthographic camera), the focus distance (to the focus object: its distance along the
    view axis), the aperture's blades, rotation and ratio; nothing with Depth of Field off
    (a pinhole) or for a camera type without it."""
    cam = obj.data
    dof = cam.dof
    if not dof.use_dof or cam.type not in ("PERSP", "ORTHO"):
        return {}
    scale = float(cam.lens) * 1e-3 if cam.type == "PERSP" else 1.0
    focus = float(dof.focus_distance)
    if dof.focus_object is not None:
        m = obj.matrix_world
        view = m.col[2].xyz.normalized()
        focus = abs(view.dot(m.translation - dof.focus_object.matrix_world.translation))
    return {
        "aperture_size": scale / (2.0 * max(float(dof.aperture_fstop), 1e-5)),
        "focus_distance": max(focus, 1e-6),
        "aperture_blades": int(dof.aperture_blades) if dof.aperture_blades >= 3 else 0,
        "aperture_rotation": float(dof.aperture_rotation),
        "aperture_ratio": float(dof.aperture_ratio),
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
