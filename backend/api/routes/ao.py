"""POST /v1/scenes/{scene_id}/ao: AO per ray for explicit rays (a binary body), exactly
`kernels.ambient_occlusion`'s, with the phases in a Server-Timing header."""

from __future__ import annotations

import time
from typing import Annotated

import numpy as np
from fastapi import APIRouter, Query, Request, Response
from scenesort.backend.api import errors, limits
from scenesort.backend.api.openapi import COMMON_ERRORS
from scenesort.backend.api.params import SceneId
from scenesort.backend.api.requests import read_body, run_on_worker, server_timing
from scenesort.backend.api.service import Shared
from scenesort.backend.render import bvhs
from scenesort.backend.render.ao import ambient_occlusion as rays_ao
from scenesort.backend.wire import binary as wire
from scenesort.backend.wire.models import OCTET, AoQuery, binary_body, error_responses
from starlette.concurrency import run_in_threadpool

router = APIRouter()


@router.post(
    "/v1/scenes/{scene_id}/ao",
    response_class=Response,
    responses={
        200: {
            "content": {OCTET: {"schema": {"type": "string", "format": "binary"}}},
            "description": "R little-endian float32 AO values, one per ray, in order; "
            "a Server-Timing header lists the phases in ms.",
        },
        **error_responses(404, *COMMON_ERRORS),
    },
    openapi_extra=binary_body(
        "R*6 little-endian float32: origin xyz then direction xyz per ray (directions "
        "need not be unit length, must be nonzero): exactly 24*R bytes."
    ),
)
async def ambient_occlusion(
    request: Request,
    scene_id: SceneId,
    service: Shared,
    query: Annotated[AoQuery, Query()],
) -> Response:
    """AO per ray, identical to `kernels.ambient_occlusion` for the same inputs (the
    scene's normals and terminator offsets included).

    Uses the BVH built with `method`/`leaf_size` when given, else the scene's most
    recently used BVH, else builds one with the defaults (sah, 8). Stops when the
    client disconnects or at the deadline (checked between the engine's rounds).
    """
    t0 = time.perf_counter()
    scene = service.scene(scene_id)
    options = query.options()
    limits.check_engine(scene, options)
    limits.check_work(service.settings.max_work, query.rays, "rays", options)
    body = await read_body(request, 24 * query.rays)
    t1 = time.perf_counter()
    try:
        origins, directions = await run_in_threadpool(wire.decode_rays, body, query.rays)
    except MemoryError as exc:
        raise errors.out_of_memory(exc) from None
    del body  # the decoded copies are what the work holds
    t2 = time.perf_counter()
    timings: dict[str, float] = {}
    signal = service.deadline()

    def work() -> np.ndarray:
        # Runs on the worker: pick or build the BVH there, never on the event loop.
        signal.check()
        w0 = time.perf_counter()
        bvh = bvhs.bvh_for_ao(service.store, scene, query.method, query.leaf_size,
                              service.settings.device)
        w1 = time.perf_counter()
        ao, engine_ms = rays_ao(bvh, scene, origins, directions, options, signal)
        timings.update(bvh=1000 * (w1 - w0), ao=1000 * (time.perf_counter() - w1))
        timings.update({f"ao.{k}": v for k, v in engine_ms.items() if k != "total"})
        return ao

    ao = await run_on_worker(request, service, signal, "rays", work)
    payload = await run_in_threadpool(wire.encode_f32, ao)
    total = 1000 * (time.perf_counter() - t0)
    all_timings = {"read": 1000 * (t1 - t0), "decode": 1000 * (t2 - t1), **timings,
                   "total": total}
    return Response(
        payload, media_type=OCTET, headers={"Server-Timing": server_timing(all_timings)}
    )
