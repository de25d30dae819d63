"""Put an AO result into the image datablock `scenesort AO` and show it."""

from __future__ import annotations

import bpy
import numpy as np

IMAGE_NAME = "scenesort AO"


def write_ao_image(ao: np.ndarray, width: int, height: int) -> bpy.types.Image:
    """Grey, linear float image of `ao` (row 0 = top row), created or resized as needed."""
    image = bpy.data.images.get(IMAGE_NAME)
    if image is None:
        image = bpy.data.images.new(IMAGE_NAME, width, height, alpha=True, float_buffer=True)
    elif tuple(image.size) != (width, height):
        image.scale(width, height)
    rgba = np.ones((height, width, 4), dtype=np.float32)
    # Image.pixels store the bottom row first; the service's rows start at the top.
    rgba[..., :3] = ao.reshape(height, width)[::-1, :, None]
    image.pixels.foreach_set(rgba.ravel())
    image.update()
    return image


def show_in_image_editors(window_manager: bpy.types.WindowManager, image: bpy.types.Image) -> int:
    """Display `image` in every open Image Editor; returns how many show it."""
    shown = 0
    for window in window_manager.windows:
        for area in window.screen.areas:
            if area.type == "IMAGE_EDITOR":
                area.spaces.active.image = image
                area.tag_redraw()
                shown += 1
    return shown
