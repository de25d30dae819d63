"""`scenesort token`: print the token `scenesort serve` uses, which its clients send."""

from __future__ import annotations

import argparse
import sys

from scenesort.backend.api.token_file import service_token, token_path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--path", action="store_true", help="print where the token file is, not the token"
    )


def run(args: argparse.Namespace) -> int:
    """Print the token a client should send (the one `scenesort serve` uses)."""
    if args.path:
        print(token_path())
        return 0
    try:
        token, _ = service_token()
    except ValueError as exc:
        print(f"scenesort token: {exc}", file=sys.stderr)
        return 2
    print(token)
    return 0
