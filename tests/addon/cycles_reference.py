"""Cycles' own Ambient Occlusion pass at pixel centres, the judge of the scenesort AO
engine (tests/addon/test_shading.py and benchmarks/cycles.py).

Cycles renders on the CPU with a 0.01-pixel Gaussian filter (its rays go through the pixel
centres, like scenesort's: BLENDER_FACTS.md), no adaptive sampling and no denoising, Film
Transparent on, into a multilayer EXR that OpenEXR reads back (Blender 5 writes one part
per pass; bpy can only show a multilayer file's first pass).
"""

from __future__ import annotations

import time
from pathlib import Path

import bpy
import numpy as np

SETTINGS = ("Cycles on the CPU, Ambient Occlusion pass, Gaussian pixel filter 0.01 px, "
            "no adaptive sampling, no denoising, Film Transparent, the World's AO distance")
# The AO pass does not depend on the light paths (BLENDER_FACTS.md): the judge renders with
# max bounces 0, which leaves the pass as it is and skips the path tracing behind it.


def exr_channels(path: Path) -> dict[str, np.ndarray]:
    """Every channel of a (multi-part) EXR by its full name ("<layer>.<pass>.<channel>"),
    as (height, width) float32, row 0 at the top (EXR's order)."""
    import OpenEXR

    out: dict[str, np.ndarray] = {}
    with OpenEXR.File(str(path), separate_channels=True) as exr:
        for part in exr.parts:
            prefix = part.name() if callable(getattr(part, "name", None)) else ""
            for name, channel in part.channels.items():
                full = name if not prefix or name.startswith(prefix) else f"{prefix}.{name}"
                out[full] = np.asarray(channel.pixels, np.float32)
    return out


def channel(channels: dict[str, np.ndarray], *names: str) -> np.ndarray:
    """The channel called one of `names` or ending in "." + one of them."""
    for key, pixels in channels.items():
        if any(key == n or key.endswith("." + n) for n in names):
            return pixels
    raise KeyError(f"none of {names} in {sorted(channels)}")


def write_cycles_ao(scene: bpy.types.Scene, path: Path, samples: int, seed: int = 0,
                    film: tuple[str, float] = ("GAUSSIAN", 0.01)) -> float:
    """F12 with Cycles (`SETTINGS`, max bounces 0) into the multilayer EXR `path` (.exr
    added); the seconds the F12 took (scene sync, BVH, render and file). The scene's render
    settings are restored afterwards. `film`: the pixel filter (type, width); Cycles'
    default is ("BLACKMAN_HARRIS", 1.5). Needs only bpy (Blender 4.2 to 5.x), so that a Python
    with nothing else can write what OpenEXR reads elsewhere."""
    render, cycles, layer = scene.render, scene.cycles, scene.view_layers[0]
    fmt = render.image_settings
    # Blender 5 chooses a multilayer file by media type, 4.x by file format.
    kind = ((fmt, "media_type", "MULTI_LAYER_IMAGE") if hasattr(fmt, "media_type")
            else (fmt, "file_format", "OPEN_EXR_MULTILAYER"))  # fmt: skip
    saved = [(render, "engine"), (render, "film_transparent"), (render, "filepath"),
             (cycles, "device"), (cycles, "samples"), (cycles, "use_adaptive_sampling"),
             (cycles, "use_denoising"), (cycles, "pixel_filter_type"),
             (cycles, "filter_width"), (cycles, "seed"), (cycles, "max_bounces"),
             (layer, "use_pass_ambient_occlusion"), kind[:2],
             (fmt, "file_format"), (fmt, "color_depth")]  # restored in this order
    before = [(owner, name, getattr(owner, name)) for owner, name in saved]
    render.engine, render.film_transparent = "CYCLES", True
    cycles.device, cycles.samples, cycles.seed, cycles.max_bounces = "CPU", samples, seed, 0
    cycles.use_adaptive_sampling, cycles.use_denoising = False, False
    cycles.pixel_filter_type, cycles.filter_width = film
    layer.use_pass_ambient_occlusion = True
    setattr(*kind)
    fmt.color_depth = "32"
    render.filepath = str(path)
    try:
        start = time.perf_counter()
        assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
        return time.perf_counter() - start
    finally:
        for owner, name, value in before:
            setattr(owner, name, value)


def read_cycles_ao(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The AO pass and alpha of `write_cycles_ao`'s file, (height, width) each with row 0
    at the top."""
    channels = exr_channels(path.with_suffix(".exr"))
    ao = channel(channels, "Ambient Occlusion.R", "AO.R")  # Blender 5 names the pass in full
    return ao, channel(channels, "Combined.A")


def render_cycles_ao(scene: bpy.types.Scene, path: Path, samples: int, seed: int = 0,
                     film: tuple[str, float] = ("GAUSSIAN", 0.01),
                     ) -> tuple[np.ndarray, np.ndarray, float]:
    """`write_cycles_ao`, then `read_cycles_ao`: the AO pass, alpha and the seconds."""
    seconds = write_cycles_ao(scene, path, samples, seed, film)
    return (*read_cycles_ao(path), seconds)


def clean_pixels(covered: np.ndarray) -> np.ndarray:
    """The pixels whose 3x3 neighbourhood is all `covered` (no edge in or next to them)."""
    padded = np.pad(covered, 1, constant_values=False)
    out = np.ones_like(covered)
    for dy in range(3):
        for dx in range(3):
            out &= padded[dy : dy + covered.shape[0], dx : dx + covered.shape[1]]
    return out


def judge(image: np.ndarray, cycles_a: np.ndarray, pixels: np.ndarray) -> tuple[float, float]:
    """`image`'s RMSE to one Cycles render over `pixels`, and how many standard errors its
    mean difference is from 0 (a bias)."""
    d = (image - cycles_a)[pixels]
    return float(np.sqrt(np.mean(d**2))), float(abs(d.mean()) / (d.std() / np.sqrt(d.size)))
