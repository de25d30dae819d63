"""What failures become: every client mistake a 4xx problem document naming the parameter
and the fix (FastAPI's own validation errors too), running out of memory a 507 or 503, the
ends of work (its deadline, its client gone, the service stopping) problems of their own,
and anything else a logged 500 after which the process carries on."""

from __future__ import annotations

import asyncio
import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from scenesort.backend.api.security import escape
from scenesort.backend.wire.problems import ApiError, busy
from scenesort.backend.work.jobs import TOO_LARGE
from scenesort.backend.work.stop import Stopped, StopSignal
from scenesort.backend.work.worker import QueueFull
from starlette.exceptions import HTTPException as StarletteHTTPException

log = logging.getLogger("scenesort.app")

SHUTDOWN = "the service is shutting down"


def gone() -> ApiError:
    return ApiError(
        400, "body", "the client disconnected", "keep the connection open for the answer",
        "client_disconnected",
    )


def engine_error(parameter: str, exc: ValueError) -> ApiError:
    """An input the engine refused (its ValueErrors name the problem): the client's to fix."""
    return ApiError(
        422,
        parameter,
        f"the engine rejected the input: {exc}",
        "correct the value named in the message",
        "rejected_by_engine",
    )


def queue_full(exc: QueueFull) -> ApiError:
    return busy(
        "request", f"the device queue is full ({exc})",
        "retry after the Retry-After seconds, when the running work has moved on",
        status=429,
    )


def out_of_memory(exc: BaseException) -> ApiError:
    """MemoryError (507) or a Warp RuntimeError, which is how its allocations fail (503)."""
    if isinstance(exc, MemoryError):
        return ApiError(507, "body", TOO_LARGE, "send a smaller scene or fewer rays",
                        "too_large")
    return busy("body", f"{TOO_LARGE} (the engine said: {exc})",
                "send a smaller scene or fewer rays, or retry when other work has finished",
                code="engine_unavailable")


def shutting_down() -> ApiError:
    return busy("request", SHUTDOWN, "retry when the service runs again", 5)


def stopped(exc: Stopped, signal: StopSignal) -> ApiError:
    if not signal.stopped:  # the deadline
        return ApiError(
            422, "rays, spp", f"the work stopped {exc}",
            "send fewer rays or samples, or start the service with a larger --max-seconds",
            "deadline",
        )
    if signal.reason == SHUTDOWN:
        return shutting_down()
    return gone()


def log_stop(done: asyncio.Future) -> None:
    """Say when work ended early (also after its client left: nobody else would know)."""
    if not done.cancelled() and isinstance(done.exception(), Stopped):
        log.info("work stopped early: %s", done.exception())


# --- the app's exception handlers -----------------------------------------------------

_FIXES = {
    "missing": "add {name}",
    "int_parsing": "send {name} as an integer",
    "int_from_float": "send {name} as an integer",
    "float_parsing": "send {name} as a finite number",
    "finite_number": "send {name} as a finite number",
    "greater_than": "use {name} > {gt}",
    "greater_than_equal": "use {name} >= {ge}",
    "less_than": "use {name} < {lt}",
    "less_than_equal": "use {name} <= {le}",
    "literal_error": "use one of {expected} for {name}",
    "extra_forbidden": "remove {name}; see /docs for the fields this route takes",
    "string_pattern_mismatch": "use an id as returned by the service ({pattern})",
    "json_invalid": "send a valid JSON object with Content-Type: application/json",
    "too_short": "give {name} the documented number of items",
    "too_long": "give {name} the documented number of items",
}


def _validation_error(_: Request, exc: RequestValidationError) -> JSONResponse:
    """FastAPI's 422 list -> one problem for the first error, naming its parameter."""
    first = exc.errors()[0]
    kind = first.get("type", "")
    loc = [str(p) for p in first.get("loc", ())]
    if loc and loc[0] in ("query", "path", "header", "body"):
        loc = loc[1:]  # where it came from is implied by the name
    name = "body" if kind == "json_invalid" or not loc else ".".join(loc)
    ctx = {k: str(v) for k, v in (first.get("ctx") or {}).items()}
    template = _FIXES.get(kind, "see /docs for {name}'s type and range")
    fix = template.format_map({"name": name, **ctx})
    got = "" if kind in ("missing", "json_invalid") else f" (got {first.get('input')!r:.80})"
    message = f"{name}: {first.get('msg')}{got}"
    status = 400 if kind == "json_invalid" else 422
    return ApiError(status, name, message, fix, "invalid_parameter").response()


def _api_error(_: Request, exc: ApiError) -> JSONResponse:
    return exc.response()


def _http_error(_: Request, exc: StarletteHTTPException) -> JSONResponse:
    parameter = {404: "path", 405: "method"}.get(exc.status_code, "request")
    fix = "see /docs for the routes and methods this service has"
    error = ApiError(exc.status_code, parameter, str(exc.detail), fix, "http_error",
                     dict(exc.headers or {}))
    return error.response()


def _memory_error(_: Request, exc: MemoryError) -> JSONResponse:
    """Out of memory anywhere in a request (reading, hashing, decoding): 507, not 500."""
    return out_of_memory(exc).response()


def _internal_error(request: Request, exc: Exception) -> JSONResponse:
    log.error("internal error on %s %s", request.method, escape(request.url.path), exc_info=exc)
    fix = "this is a service bug; the log has the traceback"
    return ApiError(
        500, "request", f"internal error: {type(exc).__name__}", fix, "internal_error"
    ).response()


def add_handlers(app: FastAPI) -> None:
    """Every exception a route can raise, as a problem document."""
    app.add_exception_handler(ApiError, _api_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(MemoryError, _memory_error)
    app.add_exception_handler(Exception, _internal_error)
