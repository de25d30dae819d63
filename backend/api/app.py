"""The HTTP API under /v1: `create_app` wires the service together.

Routes (routes/, one module per resource) decode and validate (wire/), look things up in
the store and hand heavy work to the device worker (work/); none of them runs Warp on the
event loop. security.py's `Guard` checks Host, Origin, the token and the bodies before any
route runs; errors.py turns every failure into a problem document. docs/api.md describes
the API for people, docs/security.md its defences.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI
from scenesort.backend import __version__
from scenesort.backend.api import errors
from scenesort.backend.api.openapi import with_bearer_scheme
from scenesort.backend.api.routes import ao, bvh, health, instances, jobs, meshes, scenes
from scenesort.backend.api.security import Guard
from scenesort.backend.api.service import Service, Settings
from scenesort.backend.render import engine
from starlette.concurrency import run_in_threadpool

ROUTERS = (health, scenes, meshes, instances, bvh, ao, jobs)


def create_app(settings: Settings | None = None) -> FastAPI:
    """The service's app: one store, one device worker, one job manager."""
    service = Service.start(settings or Settings())
    app = FastAPI(
        title="scenesort",
        version=__version__,
        description="BVH builds and ambient-occlusion renders over loopback. See docs/api.md.",
        lifespan=_lifespan,
    )
    app.state.service = service
    errors.add_handlers(app)
    app.add_middleware(Guard, policy=service.settings.policy)
    for module in ROUTERS:
        app.include_router(module.router)
    with_bearer_scheme(app)
    return app


@asynccontextmanager
async def _lifespan(app: FastAPI) -> AsyncIterator[None]:
    service: Service = app.state.service
    # Import the engine and load its kernels before the first request, not during it.
    await run_in_threadpool(engine.load)
    service.worker.submit(lambda: engine.warm_up(service.settings.device))
    yield
    service.stop_work()
    await run_in_threadpool(service.worker.stop, 3.0)  # the running task ends at its next round

