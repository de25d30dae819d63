"""POST /v1/scenes/{scene_id}/bvh: build (or reuse) a scene's BVH on the device worker, with
the build's per-phase timings and statistics."""

from __future__ import annotations

import time
from typing import Any

from fastapi import APIRouter, Request, Response
from scenesort.backend.api.openapi import COMMON_ERRORS
from scenesort.backend.api.params import SceneId
from scenesort.backend.api.requests import run_on_worker, server_timing
from scenesort.backend.api.service import Shared
from scenesort.backend.render import bvhs
from scenesort.backend.wire import binary as wire
from scenesort.backend.wire.models import BvhInfo, BvhRequest, BvhStats, error_responses
from scenesort.backend.wire.problems import ApiError

router = APIRouter()


@router.post("/v1/scenes/{scene_id}/bvh", response_model=BvhInfo,
             responses=error_responses(404, *COMMON_ERRORS))
async def build_bvh(
    request: Request, scene_id: SceneId, spec: BvhRequest, response: Response, service: Shared,
) -> BvhInfo:
    """Build (or reuse) the scene's BVH with these parameters; per-phase timings.

    A Server-Timing header gives the wait in the device queue and the build's wall
    time in the service (including the statistics the engine computes after it)."""
    t0 = time.perf_counter()
    scene = service.scene(scene_id)
    if isinstance(scene, wire.InstanceScene):
        raise ApiError(
            422, "scene_id",
            f"scene {scene_id} is an instance list: its two levels are built by the jobs "
            "and AO requests that render it",
            "render it (POST /v1/jobs); the job status's build says what was built",
            "instance_list",
        )
    started: list[float] = []
    signal = service.deadline()
    device = service.settings.device

    def work() -> tuple[Any, bool]:
        signal.check()  # a build cannot stop half-way: only before it starts
        started.append(time.perf_counter())
        return bvhs.get_or_build_bvh(service.store, scene, spec.method, spec.leaf_size, device)

    bvh, cached = await run_on_worker(request, service, signal, "scene", work)
    t1 = time.perf_counter()
    timings = {"queue": started[0] - t0, "build": t1 - started[0], "total": t1 - t0}
    response.headers["Server-Timing"] = server_timing({k: 1e3 * v for k, v in timings.items()})
    return _bvh_info(scene_id, spec.method, spec.leaf_size, bvh, cached)


def _bvh_info(scene_id: str, method: str, leaf_size: int, bvh: Any, cached: bool) -> BvhInfo:
    stats = bvh.stats
    timings = {"total": float(stats.build_ms)}
    timings.update({k: float(v) for k, v in stats.phase_ms.items()})
    timings["compile"] = float(stats.compile_ms)  # Warp's, not part of total
    return BvhInfo(
        scene_id=scene_id,
        method=method,
        leaf_size=leaf_size,
        cached=cached,
        timings_ms=timings,
        stats=BvhStats(**{k: getattr(stats, k) for k in BvhStats.model_fields}),
    )
