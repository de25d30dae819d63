"""Scenes by content hash: POST /v1/scenes uploads a triangle mesh in world space; HEAD and
GET /v1/scenes/{scene_id} answer for any scene the service holds (a scene, a mesh or an
instance list), with ETags, so that clients skip unchanged uploads."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request, Response
from scenesort.backend.api.params import Normals, Offsets, SceneId, Triangles, Vertices
from scenesort.backend.api.requests import etag, not_modified
from scenesort.backend.api.service import Shared
from scenesort.backend.api.uploads import (
    SCENE_LAYOUT,
    UPLOADED,
    instances_info,
    mesh_info,
    store_mesh,
)
from scenesort.backend.wire import binary as wire
from scenesort.backend.wire.models import (
    InstanceSceneInfo,
    SceneInfo,
    binary_body,
    error_responses,
)

router = APIRouter()


@router.post("/v1/scenes", **UPLOADED, openapi_extra=binary_body(SCENE_LAYOUT + " World space."))
async def upload_scene(
    request: Request, response: Response, service: Shared, vertices: Vertices,
    triangles: Triangles, normals: Normals = False, terminator_offsets: Offsets = False,
) -> SceneInfo:
    """Upload a triangle mesh; its content hash is its id (201 new, 200 known)."""
    return await store_mesh(request, response, service, (vertices, triangles),
                            (normals, terminator_offsets))


@router.head(
    "/v1/scenes/{scene_id}",
    responses={304: {"description": "If-None-Match matched"},
               404: {"description": "unknown scene"}},
)
async def has_scene(request: Request, scene_id: SceneId, service: Shared) -> Response:
    """200 if the service holds this scene, else 404: clients skip unchanged uploads."""
    if service.store.get(scene_id) is None:
        return Response(status_code=404)
    status = 304 if not_modified(request, scene_id) else 200
    return Response(status_code=status, headers={"ETag": etag(scene_id)})


@router.get(
    "/v1/scenes/{scene_id}",
    response_model=SceneInfo | InstanceSceneInfo,
    responses={304: {"description": "If-None-Match matched"}, **error_responses(404, 422)},
)
async def scene_info(request: Request, scene_id: SceneId, response: Response,
                     service: Shared) -> Any:
    """What the service knows about a scene."""
    scene = service.scene(scene_id)
    if not_modified(request, scene_id):
        return Response(status_code=304, headers={"ETag": etag(scene_id)})
    response.headers["ETag"] = etag(scene_id)
    if isinstance(scene, wire.InstanceScene):
        return instances_info(scene)
    return mesh_info(scene_id, scene)
