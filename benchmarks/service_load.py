"""The service under a mixed load: 32 clients for 60 s while renders run (docs/security.md).

    .venv/bin/python benchmarks/service_load.py [--clients 32] [--seconds 60]

Every client sends health probes, scene HEADs and conditional GETs, small uploads, BVH
builds, AO on 256 rays, small jobs (polled to the end or cancelled) and hostile requests
(wrong token, foreign Host or Origin); one 256x192, 64 spp render after another runs
throughout, followed by its event stream. Prints the answers by kind and status, the
/v1/health latency seen by a probe process (floor: p99 < 100 ms), the answers that were
not designed (floor: none but 429/503 with Retry-After) and the service's resident
memory against its budget (floor: within it). The load generator is tests/backend/load.py,
which the test suite runs for a few seconds.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.service import start_service  # noqa: E402
from tests.backend.load import OCTET, Load, rss_mb  # noqa: E402
from tests.backend.service_client import floor_and_box, scene_body  # noqa: E402

CACHE_MB, RESULTS_MB, UPLOADS_MB, WORKING_MB = 256, 64, 256, 256


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--clients", type=int, default=32)
    parser.add_argument("--seconds", type=float, default=60.0)
    args = parser.parse_args()
    proc, url, auth = start_service(
        "--cache-mb", str(CACHE_MB), "--results-mb", str(RESULTS_MB),
        "--uploads-mb", str(UPLOADS_MB),
    )
    try:
        v, i = floor_and_box()
        with httpx.Client(base_url=url, headers=auth, timeout=60) as client:
            up = client.post("/v1/scenes", params={"vertices": len(v), "triangles": len(i)},
                             content=scene_body(v, i), headers=OCTET)
            up.raise_for_status()
        idle = rss_mb(proc.pid)
        report = Load(url, auth, up.json()["scene_id"], proc.pid).run(args.clients, args.seconds)
    finally:
        proc.terminate()
        proc.wait(30)
    budget = idle + CACHE_MB + RESULTS_MB + UPLOADS_MB + WORKING_MB
    print(f"{args.clients} clients, {args.seconds:.0f} s: {report.requests} answers "
          f"({report.requests / args.seconds:.0f}/s), {report.renders} background renders")
    for (kind, status), n in sorted(report.statuses.items()):
        print(f"  {kind:8s} {status}  {n}")
    p50, p99 = report.percentile_ms(50), report.percentile_ms(99)
    worst = max(report.health_ms, default=float("nan"))
    print(f"/v1/health from a probe process: {len(report.health_ms)} probes, p50 {p50:.1f} ms, "
          f"p99 {p99:.1f} ms, max {worst:.1f} ms  [floor p99 < 100 ms: "
          f"{'met' if p99 < 100 else 'MISSED'}]")
    print(f"/v1/health as the load clients saw it (their queueing included): p50 "
          f"{report.percentile_ms(50, 'client_health_ms'):.1f} ms, p99 "
          f"{report.percentile_ms(99, 'client_health_ms'):.1f} ms")
    print(f"undesigned answers: {len(report.errors)}"
          + "".join(f"\n  {e}" for e in report.errors[:10]))
    peak = max(report.rss_mb)
    print(f"resident memory: idle {idle:.0f} MiB, peak {peak:.0f} MiB, budget {budget:.0f} MiB "
          f"(idle + cache {CACHE_MB} + results {RESULTS_MB} + uploads {UPLOADS_MB} + working "
          f"{WORKING_MB})  [{'within' if peak < budget else 'OVER'}]")
    return 0 if not report.errors and p99 < 100 and peak < budget else 1


if __name__ == "__main__":
    sys.exit(main())
