"""What FastAPI cannot infer for the schema: the bearer token's scheme (so that /docs has an
Authorize button) and the problem statuses of the routes that take bodies or run work."""

from __future__ import annotations

from typing import Any

from fastapi import FastAPI
from scenesort.backend.wire.models import error_responses

BEARER = "bearer"  # the OpenAPI security scheme of the token
COMMON_ERRORS = error_responses(400, 401, 403, 408, 413, 415, 422, 429, 503, 507)


def with_bearer_scheme(app: FastAPI) -> None:
    """Declare the token in the schema, so that /docs has an Authorize button for it."""
    make = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            schema = make()
            schema.setdefault("components", {})["securitySchemes"] = {
                BEARER: {"type": "http", "scheme": "bearer",
                         "description": "the token that `scenesort token` prints"}
            }
            schema["security"] = [{BEARER: []}]
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
