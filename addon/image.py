"""A job's outcome as Blender pixels: the render engine's passes, and the image
datablock `scenesort AO` of the panel's Render AO."""

from __future__ import annotations

import bpy
import numpy as np

from .pipeline import Outcome

IMAGE_NAME = "scenesort AO"
BACKGROUND_DEPTH = 1e10  # Cycles' Z pass where nothing was hit


def result_passes(outcome: Outcome, transparent: bool) -> dict[str, np.ndarray]:
    """The passes' pixels (bottom row first, as Blender stores them) of a job's outcome."""
    width, height = outcome.size
    coverage = outcome.coverage.reshape(height, width)[::-1].reshape(-1, 1)
    # Cycles' AO pass counts the samples that hit (premultiplied by coverage): the job's AO
    # counts a miss as 1, so a pixel's missed fraction (1 - coverage) comes off; rounding
    # of the two float32 means must not take an uncovered pixel below 0.
    ao = np.maximum(outcome.ao.reshape(height, width)[::-1].reshape(-1, 1) + coverage - 1.0,
                    0.0)
    depth = outcome.depth.reshape(height, width)[::-1].reshape(-1, 1)
    alpha = coverage if transparent else np.ones_like(coverage)
    return {"Combined": np.hstack([ao, ao, ao, alpha]), "AO": ao, "Depth": depth}


def empty_passes(width: int, height: int, transparent: bool) -> dict[str, np.ndarray]:
    """The passes of a frame where every camera ray misses (nothing to render)."""
    combined = np.zeros((width * height, 4), np.float32)
    combined[:, 3] = 0.0 if transparent else 1.0
    depth = np.full((width * height, 1), BACKGROUND_DEPTH, np.float32)
    return {"Combined": combined, "AO": combined[:, :1].copy(), "Depth": depth}


def write_ao_image(outcome: Outcome) -> bpy.types.Image:
    """The engine's Combined pass with Film > Transparent as a linear float image:
    grey AO, 0 and alpha 0 where the camera ray missed. Non-Color: AO is data, shown
    without a view transform. Created or resized as needed."""
    width, height = outcome.size
    image = bpy.data.images.get(IMAGE_NAME)
    if image is None:
        image = bpy.data.images.new(IMAGE_NAME, width, height, alpha=True, float_buffer=True)
    elif tuple(image.size) != (width, height):
        image.scale(width, height)
    image.colorspace_settings.name = "Non-Color"
    image.pixels.foreach_set(result_passes(outcome, transparent=True)["Combined"].ravel())
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
