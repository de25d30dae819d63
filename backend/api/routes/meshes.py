"""The meshes of instance lists: PUT /v1/meshes/{mesh_id} uploads one in its own space under
its content hash, HEAD says whether the service holds it."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from scenesort.backend.api.params import Normals, Offsets, SceneId, Triangles, Vertices
from scenesort.backend.api.requests import etag
from scenesort.backend.api.service import Shared
from scenesort.backend.api.uploads import SCENE_LAYOUT, UPLOADED, store_mesh
from scenesort.backend.wire import binary as wire
from scenesort.backend.wire.models import SceneInfo, binary_body

router = APIRouter()


@router.put("/v1/meshes/{mesh_id}", **UPLOADED,
            openapi_extra=binary_body(SCENE_LAYOUT + " The mesh's own (object) space."))
async def put_mesh(
    request: Request, response: Response, mesh_id: SceneId, vertices: Vertices,
    triangles: Triangles, service: Shared, normals: Normals = False,
    terminator_offsets: Offsets = False,
) -> SceneInfo:
    """Upload a mesh of an instance list under its content hash (201 new, 200 known).
    A mesh is a single-mesh scene too: its id works wherever a scene id does."""
    return await store_mesh(request, response, service, (vertices, triangles),
                            (normals, terminator_offsets), mesh_id)


@router.head(
    "/v1/meshes/{mesh_id}",
    responses={404: {"description": "unknown mesh"}},
)
async def has_mesh(mesh_id: SceneId, service: Shared) -> Response:
    """200 if the service holds this mesh, else 404: clients skip unchanged meshes."""
    if not isinstance(service.store.get(mesh_id), wire.SceneArrays):
        return Response(status_code=404)
    return Response(status_code=200, headers={"ETag": etag(mesh_id)})
