"""POST /v1/instance-scenes: a scene as an instance list over uploaded meshes, known by its
content hash; jobs render it with two levels (render/bvhs.py)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request, Response
from scenesort.backend.api.openapi import COMMON_ERRORS
from scenesort.backend.api.requests import etag, read_body
from scenesort.backend.api.service import Service, Shared
from scenesort.backend.api.uploads import instances_info, keep
from scenesort.backend.wire import binary as wire
from scenesort.backend.wire.models import InstanceSceneInfo, binary_body, error_responses
from scenesort.backend.wire.problems import ApiError
from starlette.concurrency import run_in_threadpool

router = APIRouter()


@router.post(
    "/v1/instance-scenes",
    response_model=InstanceSceneInfo,
    status_code=201,
    responses={200: {"model": InstanceSceneInfo, "description": "already known"},
               **error_responses(404, *COMMON_ERRORS)},
    openapi_extra=binary_body(
        "K*32 ASCII hex mesh ids (each PUT /v1/meshes/{mesh_id} first), then N "
        "little-endian int32 mesh indices (0-based into those ids), then N*12 float32 "
        "object-to-world transforms (3x4, row-major), then with visibility=true N uint8 "
        "ray visibility masks (1 seen by the camera, 2 occludes, 4 holdout; without them "
        "every instance is 3); exactly 32*K + 52*N bytes (53*N with masks)."
    ),
)
async def upload_instances(
    request: Request, response: Response, service: Shared,
    meshes: Annotated[int, Query(ge=1, le=2**20)],
    instances: Annotated[int, Query(ge=1, le=2**24)],
    visibility: Annotated[bool, Query(description="the body ends with N uint8 ray "
                                                  "visibility masks")] = False,
) -> InstanceSceneInfo:
    """A scene as an instance list over uploaded meshes; its content hash is its id
    (201 new, 200 known). Jobs render it with two levels: the meshes' BVHs, built once
    per mesh, and a top level over the instances."""
    body = await read_body(request, wire.instance_body_length(meshes, instances, visibility))
    listing = await run_in_threadpool(wire.decode_instances, body, meshes, instances,
                                      visibility)
    del body
    scene = service.store.get(listing.scene_id)
    if scene is None:
        scene = _resolve(listing, service)
        keep(service, listing.scene_id, scene)
    else:
        response.status_code = 200
    response.headers["Location"] = f"/v1/scenes/{listing.scene_id}"
    response.headers["ETag"] = etag(listing.scene_id)
    return instances_info(scene)


def _resolve(listing: wire.InstanceList, service: Service) -> wire.InstanceScene:
    """The list with its meshes from the store; 404 naming the first one it lacks."""
    def mesh(mesh_id: str) -> wire.SceneArrays | None:
        found = service.store.get(mesh_id)
        return found if isinstance(found, wire.SceneArrays) else None

    try:
        return wire.resolve(listing, mesh)
    except ValueError as exc:
        raise ApiError(422, "body (mesh ids)", str(exc), "upload the mesh with one "
                       "terminator offset repeated over its triangles",
                       "invalid_parameter") from None
    except KeyError as exc:
        k = listing.mesh_ids.index(exc.args[0])
        raise ApiError(
            404, "body (mesh ids)",
            f"mesh id {k} ({exc.args[0]}) is not on this service (or evicted)",
            "PUT /v1/meshes/{mesh_id} for every mesh the service lacks (HEAD tells)"
            ", then send the instance list again",
            "unknown_mesh",
        ) from None
