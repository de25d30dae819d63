"""A job's outcome as Blender pixels: the render engine's passes, and the image
datablock `scenesort AO` of the panel's Render AO."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import bpy
import numpy as np

from .export import InstanceExport, SceneMesh
from .pipeline import Outcome

IMAGE_NAME = "scenesort AO"
BACKGROUND_DEPTH = 1e10  # Cycles' Z pass where nothing was hit


@dataclass(frozen=True)
class ExtraPass:
    """A pass the view layer may turn on: Blender's definition (name, channels, channel
    ids, type), the switch (an attribute of the view layer, or of Cycles' view layer
    settings with `cycles`), the service's image it comes from (None: made here) and
    whether it needs the instance list (which object a pixel sees)."""

    blender: tuple[str, int, str, str]
    switch: str
    source: str | None
    cycles: bool = False
    per_object: bool = False


# Cycles' names and layouts, so that compositor setups made for Cycles connect as they are.
OPTIONAL_PASSES = (
    # made from the job's AO and depth (`result_passes`); Depth's Z trace only when on
    ExtraPass(("AO", 1, "X", "VALUE"), "use_pass_ambient_occlusion", None),
    ExtraPass(("Depth", 1, "Z", "VALUE"), "use_pass_z", None),
    ExtraPass(("Normal", 3, "XYZ", "VECTOR"), "use_pass_normal", "normal"),
    ExtraPass(("Position", 3, "XYZ", "VECTOR"), "use_pass_position", "position"),
    ExtraPass(("IndexOB", 1, "X", "VALUE"), "use_pass_object_index", "object", per_object=True),
    ExtraPass(("IndexMA", 1, "X", "VALUE"), "use_pass_material_index", "triangle",
              per_object=True),
    # Denoising Data: what the compositor's Denoise node takes beside the image
    ExtraPass(("Denoising Normal", 3, "XYZ", "VECTOR"), "denoising_store_passes", "normal",
              cycles=True),
    ExtraPass(("Denoising Albedo", 3, "RGB", "COLOR"), "denoising_store_passes", None,
              cycles=True),
    ExtraPass(("Denoising Depth", 1, "Z", "VALUE"), "denoising_store_passes", None,
              cycles=True),
)


def wanted_passes(view_layer: Any) -> tuple[ExtraPass, ...]:
    """The optional passes `view_layer` turns on (none without a view layer)."""
    if view_layer is None:
        return ()
    owners = {False: view_layer, True: getattr(view_layer, "cycles", None)}
    return tuple(p for p in OPTIONAL_PASSES if getattr(owners[p.cycles], p.switch, False))


def service_passes(extras: tuple[ExtraPass, ...]) -> tuple[str, ...]:
    """The service images `extras` are made from (JobRequest.passes), each once; the
    instance each pixel sees for every pass of the instance list."""
    sources = [s for p in extras for s in (("object",) if p.per_object else ()) + (p.source,)]
    return tuple(dict.fromkeys(s for s in sources if s is not None))


def needs_depth(extras: tuple[ExtraPass, ...]) -> bool:
    """Whether `extras` need the job's Z pass (a second trace of the camera rays)."""
    return any(p.blender[0] in ("Depth", "Denoising Depth") for p in extras)


def film_alpha(coverage: np.ndarray, holdout: np.ndarray | None,
               transparent: bool) -> np.ndarray:
    """Cycles' alpha from a job's coverage and holdout layer (the fraction of a pixel the
    camera sees as holdout; its samples are not covered): with Film > Transparent the
    coverage (sky and holdout alike transparent), else 1 less the holdout."""
    if transparent:
        return coverage
    return np.ones_like(coverage) if holdout is None else 1.0 - holdout


def result_passes(outcome: Outcome, transparent: bool) -> dict[str, np.ndarray]:
    """The passes' pixels (bottom row first, as Blender stores them) of a job's outcome."""
    width, height = outcome.size
    coverage = outcome.coverage.reshape(height, width)[::-1].reshape(-1, 1)
    # Cycles' AO pass counts the samples that hit (premultiplied by coverage): the job's AO
    # counts a miss as 1, so a pixel's missed fraction (1 - coverage) comes off; rounding
    # of the two float32 means must not take an uncovered pixel below 0.
    ao = np.maximum(outcome.ao.reshape(height, width)[::-1].reshape(-1, 1) + coverage - 1.0,
                    0.0)
    holdout = None if outcome.holdout is None else (
        outcome.holdout.reshape(height, width)[::-1].reshape(-1, 1))
    alpha = film_alpha(coverage, holdout, transparent)
    passes = {"Combined": np.hstack([ao, ao, ao, alpha]), "AO": ao}
    if outcome.depth is not None:  # the job traced it (the Z pass is on)
        passes["Depth"] = outcome.depth.reshape(height, width)[::-1].reshape(-1, 1)
    return passes


def extra_passes(outcome: Outcome, extras: tuple[ExtraPass, ...],
                 scene: SceneMesh | InstanceExport) -> dict[str, np.ndarray]:
    """The optional passes' pixels (bottom row first), as Cycles writes them: 0 on
    background; Object Index the object's Pass Index, Material Index its material's
    (0 on background and holdouts);
    Denoising Albedo 1 where covered (the AO image is a white surface's), Denoising Depth
    the Depth pass."""
    width, height = outcome.size

    def rows(values: np.ndarray, channels: int) -> np.ndarray:
        return values.reshape(height, width, channels)[::-1].reshape(-1, channels)

    coverage = rows(outcome.coverage, 1)
    out = {}
    for extra in extras:
        name, channels = extra.blender[:2]
        if extra.source == "object":
            index = outcome.extras["object"].astype(np.int64)
            table = np.append(getattr(scene, "pass_index", np.zeros(0)), 0.0)  # [-1]: none
            out[name] = rows(table[index].astype(np.float32), 1)
        elif extra.source == "triangle":
            halves = outcome.extras["triangle"].reshape(-1, 2).astype(np.int64)
            instance = outcome.extras["object"].astype(np.int64)
            if isinstance(scene, InstanceExport):
                index = scene.material_index(instance, halves[:, 0] * 65536 + halves[:, 1])
            else:  # a flattened scene (the DACRT engine) carries no materials
                index = np.zeros(len(instance), np.float32)
            out[name] = rows(index, 1)
        elif extra.source is not None:
            out[name] = rows(outcome.extras[extra.source], channels)
        elif name == "Denoising Albedo":
            out[name] = np.repeat(coverage, 3, axis=1)
        elif name == "Denoising Depth":
            out[name] = rows(outcome.depth, 1)
        # AO and Depth: result_passes'
    return out


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
