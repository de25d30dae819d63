"""One AO image of a scene, as `scenesort render` makes it: the BVH built (Warp's compile
time apart from the build's), then `kernels.render_ao` over the camera's rays, or
`kernels.render_film` through a pixel filter."""

from __future__ import annotations

import time
from typing import Any

import numpy as np


def build(vertices: np.ndarray, indices: np.ndarray) -> tuple[Any, float, float]:
    """The scene's BVH (the engine's defaults) and the ms Warp spent compiling and building."""
    from scenesort import kernels

    start = time.perf_counter()
    bvh = kernels.build_bvh(vertices, indices)
    compile_ms = float(bvh.stats.compile_ms)  # Warp's first use: apart
    return bvh, compile_ms, (time.perf_counter() - start) * 1e3 - compile_ms


def render_ao(bvh: Any, rays: tuple[np.ndarray, ...], options: Any, **settings: Any) -> Any:
    """`kernels.render_ao` of a camera's rays (origins, directions, tmin, tmax) with these
    AoOptions (and `render_ao`'s other keywords: image_shape, progress): its AoResult."""
    from scenesort import kernels

    origins, directions, tmin, tmax = rays
    return kernels.render_ao(bvh, origins, directions, options, tmin=tmin, tmax=tmax,
                             **settings)


def render_film(bvh: Any, camera: Any, options: Any, **settings: Any) -> Any:
    """`kernels.render_film` of `camera` with these AoOptions (and its other keywords:
    progress): its FilmResult."""
    from scenesort import kernels

    return kernels.render_film(bvh, camera, options, **settings)
