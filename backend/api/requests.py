"""What the routes do with a request: read its body, run its work on the device worker
while watching for the client leaving, and the headers they answer with (Server-Timing,
ETag)."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any

from fastapi import Request
from scenesort.backend.api import errors
from scenesort.backend.api.service import Service
from scenesort.backend.wire import binary as wire
from scenesort.backend.work.stop import Stopped, StopSignal
from scenesort.backend.work.worker import QueueFull
from starlette.requests import ClientDisconnect

DISCONNECT_POLL_S = 0.25  # how often a waiting request looks for its client having gone


async def read_body(request: Request, expected: int) -> bytes:
    """The raw body; Guard has checked its type and meters its size and pace."""
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) != expected:
        # fail before reading megabytes we would refuse
        wire.expect_body_length("the counts", int(declared), expected, "see docs/api.md")
    chunks: list[bytes] = []
    try:
        async for chunk in request.stream():
            chunks.append(chunk)
    except ClientDisconnect:  # nobody will read the answer; log a 4xx, not a traceback
        raise errors.gone() from None
    return b"".join(chunks)  # one copy at the end, not one per chunk


async def run_on_worker(
    request: Request, service: Service, signal: StopSignal, parameter: str,
    fn: Callable[[], Any],
) -> Any:
    """`fn` on the device worker; its engine failures as problems. A client that hangs up
    stops the work (queued: never starts; running: at the engine's next round)."""
    service.live.add(signal)
    try:
        future = service.worker.submit(fn)
        waiting = asyncio.wrap_future(future)
        waiting.add_done_callback(errors.log_stop)
        while not waiting.done():
            await asyncio.wait({waiting}, timeout=DISCONNECT_POLL_S)
            if waiting.done():
                break
            if await request.is_disconnected():
                signal.stop("the client disconnected")
                future.cancel()
                raise errors.gone()
            if signal.stopped and future.cancel():  # stopped while queued: never starts
                raise Stopped(signal.reason)
        if waiting.cancelled():  # the worker dropped it: the service is stopping
            raise errors.shutting_down()
        return waiting.result()
    except QueueFull as exc:
        raise errors.queue_full(exc) from None
    except ValueError as exc:
        raise errors.engine_error(parameter, exc) from None
    except Stopped as exc:
        raise errors.stopped(exc, signal) from None
    except (MemoryError, RuntimeError) as exc:
        raise errors.out_of_memory(exc) from None
    finally:
        service.live.discard(signal)


def server_timing(timings: dict[str, float]) -> str:
    return ", ".join(f"{name};dur={ms:.3f}" for name, ms in timings.items())


def etag(scene_id: str) -> str:
    return f'"{scene_id}"'


def not_modified(request: Request, scene_id: str) -> bool:
    """Whether If-None-Match names this scene's ETag (or is *)."""
    header = request.headers.get("if-none-match")
    if header is None:
        return False
    tags = {t.strip().removeprefix("W/") for t in header.split(",")}
    return "*" in tags or etag(scene_id) in tags
