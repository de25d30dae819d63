"""What clients upload, kept: a scene or mesh body read, hashed, decoded and stored by its
content hash (201 new, 200 known), and the answers that describe a stored scene."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from fastapi import Request, Response
from scenesort.backend.api import errors
from scenesort.backend.api.openapi import COMMON_ERRORS
from scenesort.backend.api.requests import etag, read_body, server_timing
from scenesort.backend.api.service import Service
from scenesort.backend.render import engine
from scenesort.backend.wire import binary as wire
from scenesort.backend.wire.models import InstanceSceneInfo, SceneInfo
from scenesort.backend.wire.problems import ApiError
from starlette.concurrency import run_in_threadpool

SCENE_LAYOUT = (
    "V*3 little-endian float32 positions, then T*3 little-endian int32 indices "
    "(0-based), then with normals=true T*9 float32 shading normals (three corners "
    "per triangle), then with terminator_offsets=true T float32 shadow terminator "
    "offsets; no header or padding: exactly 12*V + 12*T (+ 36*T) (+ 4*T) bytes."
)
UPLOADED: dict[str, Any] = {  # 201 new, 200 known: what both mesh uploads answer
    "response_model": SceneInfo, "status_code": 201,
    "responses": {200: {"model": SceneInfo, "description": "already known"}, **COMMON_ERRORS},
}


async def store_mesh(
    request: Request, response: Response, service: Service, counts: tuple[int, int],
    blocks: tuple[bool, bool], mesh_id: str | None = None,
) -> SceneInfo:
    """Read, hash, decode and keep a scene or mesh body (201 new, 200 known); with
    `mesh_id`, the body must hash to it."""
    (vertices, triangles), (normals, terminator_offsets) = counts, blocks
    t0 = time.perf_counter()
    wire.check_blocks(normals, terminator_offsets)
    expected = wire.scene_body_length(vertices, triangles, normals, terminator_offsets)
    body = await read_body(request, expected)
    t1 = time.perf_counter()
    scene_id = await run_in_threadpool(wire.scene_hash, vertices, triangles, body)
    t2 = time.perf_counter()
    if mesh_id is not None and scene_id != mesh_id:
        raise ApiError(
            422, "mesh_id", f"the body hashes to {scene_id}, not to mesh_id {mesh_id}",
            "name the mesh by its content hash (docs/api.md, the scene id rule), and send "
            "the counts and flags it was hashed with", "mesh_id_mismatch",
        )
    scene = service.store.get(scene_id)
    if scene is None:  # only new scenes pay for decoding and validation
        try:
            scene = await run_in_threadpool(
                lambda: wire.decode_scene(body, vertices, triangles, scene_id,
                                          normals=normals,
                                          terminator_offsets=terminator_offsets,
                                          count_degenerate=engine.count_degenerate)
            )
        except (MemoryError, RuntimeError) as exc:
            raise errors.out_of_memory(exc) from None
        keep(service, scene_id, scene)
    else:
        response.status_code = 200
    timings = {"read": t1 - t0, "hash": t2 - t1, "decode": time.perf_counter() - t2}
    timings["total"] = time.perf_counter() - t0
    response.headers["Server-Timing"] = server_timing({k: 1e3 * v for k, v in timings.items()})
    response.headers["Location"] = f"/v1/scenes/{scene_id}"
    response.headers["ETag"] = etag(scene_id)
    return mesh_info(scene_id, scene)


def keep(service: Service, scene_id: str, scene: Any) -> None:
    """Store a new scene, mesh or instance list; 413 if it is larger than the whole cache."""
    cache_bytes = service.settings.cache_bytes
    if scene.nbytes > cache_bytes:
        raise ApiError(
            413, "body",
            f"the scene needs {scene.nbytes} bytes of cache, more than the whole cache "
            f"({cache_bytes})",
            "start the service with a larger --cache-mb", "scene_too_large",
        )
    service.store.put(scene_id, scene, scene.nbytes)


def mesh_info(scene_id: str, scene: wire.SceneArrays) -> SceneInfo:
    return SceneInfo(
        scene_id=scene_id,
        vertices=len(scene.vertices),
        triangles=len(scene.indices),
        bounds=scene.bounds,
        degenerate=scene.degenerate,
        normals=scene.normals is not None,
        bytes=scene.nbytes,
    )


def _visibility_counts(scene: wire.InstanceScene) -> dict[str, int]:
    """Instances seen by the camera, occluding, seen as holdout."""
    n = scene.instances
    if scene.visibility is None:
        return {"camera": n, "shadow": n, "holdout": 0}
    m = scene.visibility
    return {name: int(np.count_nonzero(m & bit))
            for name, bit in (("camera", wire.CAMERA), ("shadow", wire.SHADOW),
                              ("holdout", wire.HOLDOUT))}


def instances_info(scene: wire.InstanceScene) -> InstanceSceneInfo:
    return InstanceSceneInfo(
        scene_id=scene.scene_id,
        meshes=[m.scene_id for m in scene.meshes],
        instances=scene.instances,
        triangles=scene.triangles,
        bounds=scene.bounds,
        bytes=scene.nbytes,
        visibility=_visibility_counts(scene),
    )
