"""The HTTP server: uvicorn with its httptools protocol, and what uvicorn lacks for a service
that any local process can reach.

- A deadline on the request head. uvicorn has no timeout for a request line and headers that
  arrive slowly: a client sending its head one byte at a time held its connection for ever.
  Here a connection that has not sent a whole head within `head_timeout_s` of opening (on a
  kept-alive connection: of its next request's first byte) is closed.
- A bound on the request head's bytes (431 past MAX_HEAD_BYTES): httptools keeps a header
  whole until it ends, so one client streaming an endless header grew the process by 124 MB
  in the 4.5 s the deadline left it (measured).
- Requests are counted, not connections. uvicorn's `limit_concurrency` counts every open
  connection, those still sending their head included, so 300 slow heads made it answer 503
  to everyone, the token holder too. It is off here: the middleware (security.py), which sees
  only whole heads, caps the requests in flight, the token holder's apart from strangers'.
"""

from __future__ import annotations

import asyncio
import functools
import logging
from typing import Any

import uvicorn
from fastapi import FastAPI
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

log = logging.getLogger("scenesort.server")

HEAD_TIMEOUT_S = 5.0  # default of serve --head-timeout
MAX_HEAD_BYTES = 64 * 2**10  # request line and headers; browsers send a few KiB at most
TOO_LARGE = b"request head over %d bytes" % MAX_HEAD_BYTES


class HeadDeadlineProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol with a deadline and a size bound on every request head."""

    def __init__(self, *args: Any, head_timeout_s: float, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.head_timeout_s = head_timeout_s
        self._head_timer: asyncio.TimerHandle | None = None
        self._head_bytes = 0

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._start_head_timer()

    def data_received(self, data: bytes) -> None:
        in_head = self._head_timer is not None
        super().data_received(data)
        # Counted: chunks that are all head. A chunk in which a head starts (after a kept-
        # alive request's end) is not, so a pipelined request is never refused for it.
        if in_head and self._head_timer is not None:
            self._head_bytes += len(data)
            if self._head_bytes > MAX_HEAD_BYTES:
                self._refuse_head()

    def on_message_begin(self) -> None:
        super().on_message_begin()
        self._start_head_timer()  # a kept-alive connection's next request: its own deadline

    def on_headers_complete(self) -> None:
        self._stop_head_timer()
        super().on_headers_complete()

    def connection_lost(self, exc: Exception | None) -> None:
        self._stop_head_timer()
        super().connection_lost(exc)

    def _start_head_timer(self) -> None:
        if self._head_timer is None:
            self._head_timer = self.loop.call_later(self.head_timeout_s, self._head_too_slow)
            self._head_bytes = 0

    def _stop_head_timer(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None

    def _head_too_slow(self) -> None:
        self._head_timer = None
        log.debug("dropped %s: no whole request head in %.1f s", self.client, self.head_timeout_s)
        self.shutdown()  # closes now, or after the answer a pipelined request is writing

    def _refuse_head(self) -> None:
        self._stop_head_timer()
        if self.cycle is not None and not self.cycle.response_complete:
            self.transport.close()  # an answer is being written: no room for another
            return
        self.transport.write(
            b"HTTP/1.1 431 Request Header Fields Too Large\r\ncontent-type: text/plain; "
            b"charset=utf-8\r\ncontent-length: %d\r\nconnection: close\r\n\r\n%s"
            % (len(TOO_LARGE), TOO_LARGE))
        self.transport.close()


def server(app: FastAPI, log_level: str = "info",
           head_timeout_s: float = HEAD_TIMEOUT_S) -> uvicorn.Server:
    """uvicorn's server for the app, told to stop the work before it waits for connections
    to close."""

    class Server(uvicorn.Server):
        def handle_exit(self, sig: int, frame: Any) -> None:
            app.state.service.stop_work()  # in-flight renders end at their next round (503)
            super().handle_exit(sig, frame)

    config = uvicorn.Config(
        app,
        http=functools.partial(HeadDeadlineProtocol, head_timeout_s=head_timeout_s),
        log_level=log_level,
        access_log=False,  # Guard logs one line per request with its duration
        timeout_graceful_shutdown=3,
        limit_concurrency=None,  # Guard counts requests; see the module's docstring
    )
    return Server(config)
