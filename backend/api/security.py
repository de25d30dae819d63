"""What stands between the network and the routes: one pure-ASGI middleware, `Guard`.

In order, for every HTTP request (docs/security.md says what each check stops):

1. Host must name this service (loopback names with the bound port, or an allowed host):
   a page whose domain was rebound to 127.0.0.1 sends its own name and gets 403.
2. Origin, when present, must be the service's own (its /docs page) or on the allowlist
   (empty by default): browsers send it with every cross-site fetch, `no-cors` ones
   included (403).
3. A cap on requests in flight (503 with Retry-After), counted apart for requests with the
   token and without it, so that strangers cannot take the token holder's places;
   /v1/health is exempt. (Connections still sending their head are not requests yet:
   server.py gives them a deadline.)
4. The bearer token on every route but /v1/health and the schema pages (401): scheme
   case-insensitive, compared in constant time.
5. POST and PUT bodies: the declared Content-Type of the route (415); JSON bodies at most
   `max_json_bytes`, refused from Content-Length or as soon as the stream passes it
   (413); binary bodies at most `max_body_bytes` and within a budget of bytes in flight
   over all uploads (503); every body must keep arriving (408 for a slow one).
6. One log line per request, control characters escaped so a `%0a` cannot forge lines.

Pure ASGI (not BaseHTTPMiddleware) so that streamed responses and client disconnects
pass straight through.
"""

from __future__ import annotations

import asyncio
import logging
import re
import secrets
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

from scenesort.backend.wire.models import OCTET
from scenesort.backend.wire.problems import ApiError, busy

log = logging.getLogger("scenesort.app")

JSON = "application/json"
LOOPBACK_NAMES = frozenset({"localhost", "127.0.0.1", "[::1]"})
OPEN_PATH = "/v1/health"  # answers without the token, and then only status and versions
# Also without the token: the API's schema and its page (no data; Swagger's Authorize
# button then takes the token, which a browser could not otherwise add to /docs).
PUBLIC_PATHS = frozenset({OPEN_PATH, "/openapi.json", "/docs"})
AUTHORIZED = "scenesort.authorized"  # scope key the middleware sets for the routes
# raw little-endian bodies: scenes, rays, surface points, meshes, instance lists
_BINARY_ROUTES = re.compile(
    r"^/v1/(scenes(/[^/]+/(ao|surface-jobs))?|meshes/[^/]+|instance-scenes)$")
BODY_METHODS = frozenset({"POST", "PUT"})  # the methods whose bodies are checked and metered
_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f\\]")

Receive = Callable[[], Awaitable[dict]]
Send = Callable[[dict], Awaitable[None]]


@dataclass(frozen=True)
class Policy:
    """The limits `scenesort serve` configures (defaults are its defaults)."""

    token: str | None = None
    port: int | None = None  # the bound port; None accepts any (an app not bound by serve)
    hosts: frozenset[str] = frozenset()  # accepted Host names besides loopback's
    origins: frozenset[str] = frozenset()  # accepted Origin values, e.g. http://host:port
    max_json_bytes: int = 64 * 2**10
    max_body_bytes: int = 512 * 2**20
    upload_bytes: int = 1024 * 2**20  # binary bytes in flight over all uploads at once
    body_timeout_s: float = 30.0  # allowance to send any body ...
    min_body_rate: float = 2**20  # ... plus its length at this many bytes per second
    max_requests: int = 64  # requests in flight with the token, and as many without it;
    # /v1/health not counted


def escape(text: str) -> str:
    """`text` with control characters and backslashes as \\xNN: one log line stays one."""
    return _CONTROL.sub(lambda m: f"\\x{ord(m.group()):02x}", text)


def _header(scope: dict, name: bytes) -> str | None:
    for key, value in scope.get("headers", ()):
        if key == name:
            return value.decode("latin-1")
    return None


def _split_host(value: str) -> tuple[str, int | None]:
    """("name", port) of a Host header; names lower-cased, IPv6 kept in brackets."""
    value = value.strip().lower()
    name, sep, port = value.rpartition(":")
    if not sep or name.endswith(":") or (value.startswith("[") and not name.endswith("]")):
        return value, None  # no port (an IPv6 literal's colons are not one)
    return (name, int(port)) if port.isdigit() else (value, -1)


@dataclass
class Guard:
    """The middleware; `policy` fixed at start, counters shared by all requests."""

    app: Any
    policy: Policy = field(default_factory=Policy)
    requests: int = 0  # in flight with the token (or with none needed)
    strangers: int = 0  # in flight without it
    upload_bytes: int = 0

    async def __call__(self, scope: dict, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = [0]

        async def send_logged(message: dict) -> None:
            if message["type"] == "http.response.start":
                status[0] = message["status"]
            await send(message)

        scope[AUTHORIZED] = authorized = self._authorized(scope)
        counted = scope["path"] != OPEN_PATH
        reserved = [0]
        try:
            self._count(counted, authorized, +1)
            problem = self._refusal(scope)
            if problem is None:
                receive, problem = await self._body(scope, receive, reserved)
            if problem is not None:
                await problem.response()(scope, receive, send_logged)
            else:
                await self.app(scope, receive, send_logged)
        except BaseException:
            status[0] = status[0] or 500  # ServerErrorMiddleware, outside us, answers 500
            raise
        finally:
            self._count(counted, authorized, -1)
            self.upload_bytes -= reserved[0]
            query = scope.get("query_string", b"").decode("latin-1")
            path = escape(scope["path"] + (f"?{query}" if query else ""))
            ms = 1000.0 * (time.perf_counter() - start)
            log.info("%s %s -> %s in %.1f ms", escape(scope["method"]), path,
                     status[0] or "-", ms)

    # --- checks on the request line and headers ---------------------------------------

    def _refusal(self, scope: dict) -> ApiError | None:
        """The first check the request fails, or None; nothing of the body is read."""
        host = _header(scope, b"host")
        if not self._host_allowed(host):
            return ApiError(
                403, "Host", f"Host {escape(str(host))!r} is not this service's name",
                "connect to http://127.0.0.1:PORT (or a name given to serve --allow-host)",
                "foreign_host",
            )
        origin = _header(scope, b"origin")
        # The Host check passed, so an Origin naming that host is this service's own page.
        own = f"http://{str(host).strip().lower()}"
        if origin is not None and origin != own and origin not in self.policy.origins:
            return ApiError(
                403, "Origin", f"requests from web pages at {escape(origin)!r} are not allowed",
                "call the service from a program, or start it with --allow-origin ORIGIN",
                "foreign_origin",
            )
        if scope["path"] != OPEN_PATH:
            problem = self._over_cap(scope[AUTHORIZED])
            if problem is not None:
                return problem
        if scope["path"] not in PUBLIC_PATHS and not scope[AUTHORIZED]:
            return ApiError(
                401, "Authorization", "missing or wrong bearer token",
                "send 'Authorization: Bearer TOKEN' with the token `scenesort token` prints "
                "(or the $SCENESORT_TOKEN the service was started with)",
                "unauthorized",
            )
        if scope["method"] in BODY_METHODS:
            return self._content_problem(scope)
        return None

    def _count(self, counted: bool, authorized: bool, step: int) -> None:
        if counted and authorized:
            self.requests += step
        elif counted:
            self.strangers += step

    def _over_cap(self, authorized: bool) -> ApiError | None:
        """503 past the cap of the request's own pool: with the token, or without it."""
        cap = self.policy.max_requests
        if authorized and self.requests > cap:
            return busy("request", f"{cap} requests are in flight",
                        "retry after the Retry-After seconds")
        if not authorized and self.strangers > cap:
            return busy("request", f"{cap} requests without the token are in flight",
                        "retry after the Retry-After seconds")
        return None

    def _host_allowed(self, host: str | None) -> bool:
        if host is None:
            return False
        name, port = _split_host(host)
        if name not in LOOPBACK_NAMES and name not in self.policy.hosts:
            return False
        bound = self.policy.port
        return bound is None or port == bound or (port is None and bound == 80)

    def _authorized(self, scope: dict) -> bool:
        if self.policy.token is None:
            return True
        scheme, _, credentials = (_header(scope, b"authorization") or "").strip().partition(" ")
        return scheme.lower() == "bearer" and secrets.compare_digest(
            credentials.strip().encode(), self.policy.token.encode()
        )

    def _content_problem(self, scope: dict) -> ApiError | None:
        binary = _BINARY_ROUTES.match(scope["path"]) is not None
        expected = OCTET if binary else JSON
        ctype = (_header(scope, b"content-type") or "").split(";")[0].strip().lower()
        if ctype != expected:
            return ApiError(
                415, "Content-Type", f"body must be {expected}, got {ctype or 'none'!r}",
                f"send the body with Content-Type: {expected}", "bad_content_type",
            )
        declared = _header(scope, b"content-length")
        limit = self.policy.max_body_bytes if binary else self.policy.max_json_bytes
        if declared is not None and declared.strip().isdigit() and int(declared) > limit:
            return _too_big(binary, limit)
        return None

    # --- the body -----------------------------------------------------------------------

    async def _body(
        self, scope: dict, receive: Receive, reserved: list[int]
    ) -> tuple[Receive, ApiError | None]:
        """The receive the app gets: JSON bodies read here whole (bounded), binary ones
        metered as they stream; or the problem that ends the request now."""
        if scope["method"] not in BODY_METHODS:
            return receive, None
        if _BINARY_ROUTES.match(scope["path"]) is None:
            return await self._json_body(receive)
        declared = _header(scope, b"content-length")
        if declared is not None and declared.strip().isdigit():
            problem = self._reserve(int(declared), reserved)
            if problem is not None:
                return receive, problem
        return self._metered(receive, reserved, declared is None), None

    def _deadline(self, start: float, received: int) -> float:
        return start + self.policy.body_timeout_s + received / self.policy.min_body_rate

    async def _json_body(self, receive: Receive) -> tuple[Receive, ApiError | None]:
        start, chunks, size = time.monotonic(), [], 0
        more = True
        while more:
            try:
                async with asyncio.timeout_at(_loop_time(self._deadline(start, size))):
                    message = await receive()
            except TimeoutError:
                return receive, _slow_body()
            if message["type"] == "http.disconnect":
                return receive, None  # the app sees the disconnect on its own read
            chunks.append(message.get("body", b""))
            size += len(chunks[-1])
            if size > self.policy.max_json_bytes:
                return receive, _too_big(False, self.policy.max_json_bytes)
            more = message.get("more_body", False)
        replay = [{"type": "http.request", "body": b"".join(chunks), "more_body": False}]

        async def replayed() -> dict:
            return replay.pop() if replay else await receive()

        return replayed, None

    def _reserve(self, nbytes: int, reserved: list[int]) -> ApiError | None:
        if self.upload_bytes + nbytes > self.policy.upload_bytes:
            return busy(
                "body", f"uploads in flight already hold {self.upload_bytes} of the "
                f"service's {self.policy.upload_bytes} bytes for request bodies",
                "retry after the Retry-After seconds, or send fewer uploads at once",
            )
        self.upload_bytes += nbytes
        reserved[0] += nbytes
        return None

    def _metered(self, receive: Receive, reserved: list[int], chunked: bool) -> Receive:
        """`receive` that raises ApiError (the app's handlers answer it) for a body past
        the limit, past the upload budget (chunked bodies reserve as they arrive) or too
        slow; once the body is whole it is `receive` itself."""
        start, size, done = time.monotonic(), [0], [False]

        async def metered() -> dict:
            if done[0]:
                return await receive()
            try:
                async with asyncio.timeout_at(_loop_time(self._deadline(start, size[0]))):
                    message = await receive()
            except TimeoutError:
                raise _slow_body() from None
            chunk = len(message.get("body", b""))
            size[0] += chunk
            done[0] = not message.get("more_body", False)
            if size[0] > self.policy.max_body_bytes:
                raise _too_big(True, self.policy.max_body_bytes)
            if chunked:
                problem = self._reserve(chunk, reserved)
                if problem is not None:
                    raise problem
            return message

        return metered


def _loop_time(monotonic_deadline: float) -> float:
    """A time.monotonic() deadline on the event loop's clock."""
    loop = asyncio.get_running_loop()
    return loop.time() + (monotonic_deadline - time.monotonic())


def _too_big(binary: bool, limit: int) -> ApiError:
    fix = (
        "send a smaller scene/fewer rays, or start the service with a larger --max-body-mb"
        if binary
        else f"JSON bodies are at most {limit} bytes; send the documented fields only"
    )
    return ApiError(413, "body", f"body exceeds the limit of {limit} bytes", fix,
                    "body_too_large")


def _slow_body() -> ApiError:
    return ApiError(
        408, "body", "the body did not arrive in time",
        "send the whole body without pauses (the service allows --body-timeout seconds "
        "plus 1 s per MiB)",
        "slow_body",
    )
