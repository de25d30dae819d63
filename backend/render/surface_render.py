"""AO at explicit surface points, the work of a surface job (a bake's texels): the scene's
BVH (cached or built), then `kernels.surface_ao` with the scene's normals and progress."""

from __future__ import annotations

from typing import Any

import numpy as np
from scenesort.backend.render.ao import shading
from scenesort.backend.render.bvhs import scene_bvh
from scenesort.backend.work.jobs import Job

from scenesort.ao_options import AoOptions


def render_surface(
    job: Job, store: Any, scene: Any, points: tuple[np.ndarray, np.ndarray, np.ndarray],
    options: AoOptions, method: str, leaf_size: int, device: str,
) -> None:
    """AO at `points` (triangles, u, v) into `job`: ao (1, P), coverage (1 where the point
    was shaded, 0 on a triangle without area), statistics and timings."""
    from scenesort import kernels

    bvh, job.build = job.timed("bvh", lambda: scene_bvh(store, scene, method, leaf_size,
                                                       device, None))

    def progress(fraction: float, phase: str) -> None:
        job.report(f"ao.{phase}", fraction)  # raises Stopped inside the engine's loop

    result = job.timed("ao", lambda: kernels.surface_ao(bvh, *points, options,
                                                        progress=progress, **shading(scene)))
    for name, ms in result.timings_ms.to_dict().items():
        job.add_timing(f"ao.{name}", float(ms))
    job.ao = np.asarray(result.ao, dtype=np.float32).reshape(1, -1)
    job.coverage = (result.spp_used > 0).astype(np.float32).reshape(1, -1)
    stats = result.stats()
    job.spp_mean, job.spp_max = stats.spp_mean, stats.spp_max
    job.rmse_estimate, job.rays, job.denoised = stats.rmse_estimate, stats.rays, False
