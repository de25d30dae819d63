"""`scenesort serve`: run the HTTP service (backend/app.py) under uvicorn.

Binds the socket itself so that `--port 0` works: the first line on stdout is
`scenesort serving on http://HOST:PORT ...` with the port actually bound (tests and
the add-on read it). Refuses to listen beyond loopback without a token.
"""

from __future__ import annotations

import argparse
import ipaddress
import logging
import os
import socket
import sys

TOKEN_ENV = "SCENESORT_TOKEN"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `scenesort serve`."""
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (default loopback)")
    parser.add_argument("--port", type=int, default=8765, help="TCP port; 0 picks a free one")
    parser.add_argument("--device", default="cpu", help="Warp device: cpu or cuda:0 (default cpu)")
    parser.add_argument(
        "--token",
        default=os.environ.get(TOKEN_ENV),
        help=f"bearer token clients must send (default: ${TOKEN_ENV}); required off loopback",
    )
    parser.add_argument("--max-body-mb", type=float, default=512.0, help="largest request body")
    parser.add_argument("--cache-mb", type=float, default=2048.0, help="scene+BVH cache budget")
    parser.add_argument("--log-level", default="info", choices=["debug", "info", "warning"])


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
    if not is_loopback(args.host) and not args.token:
        return (
            f"refusing to listen on {args.host}: it is reachable from other machines and "
            f"there is no --token (or ${TOKEN_ENV}), so anyone could use this service. "
            "Pass --token SECRET (clients then send 'Authorization: Bearer SECRET') "
            "or keep the default --host 127.0.0.1."
        )
    if not 0 <= args.port <= 65535:
        return f"--port must be in 0..65535, got {args.port}"
    if args.max_body_mb <= 0 or args.cache_mb <= 0:
        return "--max-body-mb and --cache-mb must be > 0"
    return None


def _check_device(device: str) -> str | None:
    """None if Warp has `device`, else a message listing the devices it has."""
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING  # no greeting: stdout is for the 'serving on' line
    wp.init()
    try:
        wp.get_device(device)
    except (RuntimeError, ValueError):
        names = [str(d) for d in wp.get_devices()]
        return f"--device {device!r} is not available here; this machine has {names}"
    return None


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
    problem = _problem(args) or _check_device(args.device)
    if problem:
        print(f"scenesort serve: {problem}", file=sys.stderr)
        return 2
    logging.basicConfig(
        level=args.log_level.upper(),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    import uvicorn

    from backend.app import Settings, create_app

    settings = Settings(
        device=args.device,
        token=args.token,
        max_body_bytes=int(args.max_body_mb * 2**20),
        cache_bytes=int(args.cache_mb * 2**20),
    )
    family = socket.AF_INET6 if ":" in args.host else socket.AF_INET
    try:
        sock = _listen(family, args.host, args.port)
    except OSError as exc:
        print(f"scenesort serve: cannot bind {args.host}:{args.port}: {exc}", file=sys.stderr)
        return 2
    host, port = sock.getsockname()[:2]
    shown = f"[{host}]" if family == socket.AF_INET6 else host
    print(f"scenesort serving on http://{shown}:{port} (device {args.device})", flush=True)
    config = uvicorn.Config(
        create_app(settings),
        log_level=args.log_level,
        access_log=False,  # AccessMiddleware logs one line per request with its duration
        timeout_graceful_shutdown=5,
    )
    uvicorn.Server(config).run(sockets=[sock])
    return 0
