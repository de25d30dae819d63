"""The service while slow clients hold connections: /v1/health with and without the token.

    .venv/bin/python benchmarks/slow_clients.py [--connections 300] [--seconds 10]

Opens `--connections` loopback connections to a real `scenesort serve` that send a request
head one byte every 50 ms and never finish it (tests/backend/dribble.py; a dropped one is
replaced at once), then for `--seconds` sends GET /v1/health on a new connection every
100 ms, in turn with the token and without it. Prints the statuses and latencies of each
and how many slow connections the service dropped. Floor (docs/security.md): with 300
such connections, /v1/health with the token answers 200 within 1 s.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections import Counter
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.service import start_service  # noqa: E402
from tests.backend.dribble import Dribblers  # noqa: E402

FLOOR_S = 1.0


def probe(url: str, headers: dict[str, str]) -> tuple[int | str, float]:
    """One GET /v1/health on a new connection: (status or error name, seconds)."""
    t0 = time.perf_counter()
    try:
        status: int | str = httpx.get(f"{url}/v1/health", headers=headers,
                                      timeout=10).status_code
    except httpx.HTTPError as exc:
        status = type(exc).__name__
    return status, time.perf_counter() - t0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--connections", type=int, default=300)
    parser.add_argument("--seconds", type=float, default=10.0)
    args = parser.parse_args()
    proc, url, auth = start_service()
    host, port = url.removeprefix("http://").rsplit(":", 1)
    results: dict[str, list[tuple[int | str, float]]] = {"token": [], "no token": []}
    try:
        with Dribblers(host, int(port), args.connections) as slow:
            time.sleep(1.0)  # every connection has sent a few bytes of its head
            stop_at = time.monotonic() + args.seconds
            while time.monotonic() < stop_at:
                for name, headers in (("token", auth), ("no token", {})):
                    results[name].append(probe(url, headers))
                time.sleep(0.1)
            dropped, held = slow.dropped, slow.open
    finally:
        proc.terminate()
        proc.wait(30)
    print(f"{args.connections} connections dribbling a request head (1 byte / 50 ms) for "
          f"{args.seconds:.0f} s: the service dropped {dropped}, {held} held at the end")
    ok = True
    for name, answers in results.items():
        statuses = Counter(status for status, _ in answers)
        ms = sorted(1e3 * s for _, s in answers)
        p50, worst = statistics.median(ms), ms[-1]
        print(f"  /v1/health, {name:8s}: {dict(statuses)}; p50 {p50:.1f} ms, max {worst:.1f} ms")
        if name == "token":
            ok = set(statuses) == {200} and worst < 1e3 * FLOOR_S
    print(f"floor: every /v1/health with the token 200 within {FLOOR_S:.0f} s: "
          f"{'met' if ok else 'MISSED'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
