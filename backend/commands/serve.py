"""`scenesort serve`: run the HTTP service (api/app.py) under uvicorn (api/server.py).

Binds the socket itself so that `--port 0` works: the first line on stdout is
`scenesort serving on http://HOST:PORT (device D, token ...)` with the port actually bound
(tests and the add-on read it) and where the token came from. There is always a token
(api/token_file.py) unless `--no-token`, which only loopback allows. SIGTERM and SIGINT
cancel the running and queued work first, so the process exits within seconds even with
a long render in flight.
"""

from __future__ import annotations

import argparse
import contextlib
import ipaddress
import logging
import os
import socket
import sys
from typing import Any

from scenesort.backend.api import lifeline
from scenesort.backend.api.server import HEAD_TIMEOUT_S, server
from scenesort.backend.api.token_file import TOKEN_ENV, service_token
from scenesort.backend.render import engine

log = logging.getLogger("scenesort.serve")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `scenesort serve`."""
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (default loopback)")
    parser.add_argument("--port", type=int, default=8765, help="TCP port; 0 picks a free one")
    parser.add_argument("--device", default="cpu", help="Warp device: cpu or cuda:0 (default cpu)")
    parser.add_argument(
        "--no-token",
        action="store_true",
        help=f"accept requests without a token (loopback only; default: ${TOKEN_ENV}, else "
        "a generated one in a user-only file, see `scenesort token`)",
    )
    parser.add_argument("--allow-origin", action="append", default=[], metavar="ORIGIN",
                        help="a web origin (scheme://host:port) whose pages may call the "
                        "service; repeatable (default: none)")
    parser.add_argument("--allow-host", action="append", default=[], metavar="NAME",
                        help="a Host name besides loopback's that clients use; repeatable")
    parser.add_argument("--max-body-mb", type=float, default=512.0, help="largest request body")
    parser.add_argument("--uploads-mb", type=float, default=1024.0,
                        help="request-body bytes in flight over all uploads at once")
    parser.add_argument("--cache-mb", type=float, default=2048.0, help="scene+BVH cache budget")
    parser.add_argument("--results-mb", type=float, default=512.0,
                        help="finished jobs' images kept (oldest forgotten first)")
    parser.add_argument("--max-work", type=int, default=2**32,
                        help="ray casts per request or job (rays x spp; default 2^32)")
    parser.add_argument("--max-seconds", type=float, default=1800.0,
                        help="deadline of a request's or a job's work, in seconds")
    parser.add_argument("--max-connections", type=int, default=64,
                        help="requests in flight with the token (more get 503), and as many "
                        "without it")
    parser.add_argument("--body-timeout", type=float, default=30.0,
                        help="seconds allowed for any body, plus 1 s per MiB of it (else 408)")
    parser.add_argument("--head-timeout", type=float, default=HEAD_TIMEOUT_S,
                        help="seconds a connection has to send a whole request head (request "
                        f"line and headers) before it is closed (default {HEAD_TIMEOUT_S:g})")
    parser.add_argument("--log-level", default="info", choices=["debug", "info", "warning"])
    parser.add_argument("--exit-with-stdin", action="store_true",
                        help="stop when stdin closes (the add-on holds a pipe open: the service "
                        "ends with Blender on every OS)")


def is_loopback(host: str) -> bool:
    """Whether `host` only accepts connections from this machine."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a hostname: it may resolve to anything


def _problem(args: argparse.Namespace) -> str | None:
    """Why these options cannot start a service, or None."""
    if not is_loopback(args.host) and args.no_token:
        return (
            f"refusing --no-token on {args.host}: it is reachable from other machines, so "
            "anyone could use this service. Drop --no-token (clients then send the token "
            "`scenesort token` prints) or keep the default --host 127.0.0.1."
        )
    if not 0 <= args.port <= 65535:
        return f"--port must be in 0..65535, got {args.port}"
    positive = ("max_body_mb", "uploads_mb", "cache_mb", "results_mb", "max_work", "max_seconds",
                "max_connections", "body_timeout", "head_timeout")
    bad = [f"--{name.replace('_', '-')}" for name in positive if not getattr(args, name) > 0]
    if bad:
        return f"{', '.join(bad)} must be > 0"
    return None


def _token(args: argparse.Namespace) -> tuple[str | None, str]:
    """The token and how the first line describes it."""
    if args.no_token:
        return None, "no token"
    token, source = service_token()
    return token, f"token {'from' if source.startswith('$') else 'in'} {source}"


def _listen(family: socket.AddressFamily, host: str, port: int) -> socket.socket:
    """A listening TCP socket. The protocol is given explicitly: asyncio turns Nagle off
    (TCP_NODELAY) only on sockets whose proto is IPPROTO_TCP, and without that every
    keep-alive response waits ~40 ms for a delayed ACK."""
    sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host, port))
        sock.listen(128)
    except OSError:
        sock.close()
        raise
    return sock


def run(args: argparse.Namespace) -> int:
    """Start uvicorn; return its exit status (2 for refused options)."""
    problem = _problem(args) or engine.device_problem(args.device)
    token, described = None, ""
    if problem is None:
        try:
            token, described = _token(args)
        except (ValueError, OSError) as exc:
            problem = f"no token: {exc}"
    if problem:
        print(f"scenesort serve: {problem}", file=sys.stderr)
        return 2
    logging.basicConfig(
        level=args.log_level.upper(),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    family = socket.AF_INET6 if ":" in args.host else socket.AF_INET
    try:
        sock = _listen(family, args.host, args.port)
    except OSError as exc:
        print(f"scenesort serve: cannot bind {args.host}:{args.port}: {exc}", file=sys.stderr)
        return 2
    if args.exit_with_stdin:
        # Only now: a refusal above must exit with its message, and a thread blocked in
        # reading stdin makes the interpreter's shutdown abort (its buffer's lock is held).
        # A parent that died meanwhile is seen at the first read.
        lifeline.exit_with_stdin()
    host, port = sock.getsockname()[:2]
    shown = f"[{host}]" if family == socket.AF_INET6 else host
    app = _app(args, token, port, shown)
    print(f"scenesort serving on http://{shown}:{port} (device {args.device}, {described})",
          flush=True)
    with contextlib.suppress(KeyboardInterrupt):  # uvicorn re-raises the SIGINT it handled
        server(app, args.log_level, args.head_timeout).run(sockets=[sock])
    # A launch that ignored the cancel: do not wait on it.
    if not app.state.service.worker.stop(0.0):
        log.warning("the device worker is still in a kernel launch; exiting without it")
        logging.shutdown()
        os._exit(0)
    return 0


def _app(args: argparse.Namespace, token: str | None, port: int, shown: str) -> Any:
    from scenesort.backend.api.app import create_app
    from scenesort.backend.api.security import Policy
    from scenesort.backend.api.service import Settings

    hosts = {name.lower() for name in args.allow_host}
    if not is_loopback(args.host) and not ipaddress.ip_address(shown.strip("[]")).is_unspecified:
        hosts.add(shown.lower())
    policy = Policy(
        token=token,
        port=port,
        hosts=frozenset(hosts),
        origins=frozenset(args.allow_origin),
        max_body_bytes=int(args.max_body_mb * 2**20),
        upload_bytes=int(args.uploads_mb * 2**20),
        body_timeout_s=args.body_timeout,
        max_requests=args.max_connections,
    )
    return create_app(Settings(
        device=args.device,
        cache_bytes=int(args.cache_mb * 2**20),
        result_bytes=int(args.results_mb * 2**20),
        max_work=args.max_work,
        max_seconds=args.max_seconds,
        policy=policy,
    ))
