"""GET /v1/health: liveness and versions for anyone; with the token also the device, the
cache, the queue and the jobs."""

from __future__ import annotations

from fastapi import APIRouter, Request
from scenesort.backend import __version__
from scenesort.backend.api.openapi import BEARER
from scenesort.backend.api.security import AUTHORIZED
from scenesort.backend.api.service import Shared
from scenesort.backend.render import engine
from scenesort.backend.wire.models import CacheUse, Health

router = APIRouter()


@router.get("/v1/health", response_model=Health, response_model_exclude_none=True,
            openapi_extra={"security": [{}, {BEARER: []}]})  # the token is optional here
async def health(request: Request, service: Shared) -> Health:
    """Liveness and versions; with the token also the device, cache and queue."""
    if not request.scope.get(AUTHORIZED):
        return Health(version=__version__, warp_version=engine.warp_version())
    return Health(
        version=__version__,
        warp_version=engine.warp_version(),
        device=service.settings.device,
        devices=engine.devices(),
        cache=CacheUse(**service.store.usage()),
        queued=service.worker.queued,
        active_jobs=service.jobs.active(),
        max_body_bytes=service.settings.policy.max_body_bytes,
    )
