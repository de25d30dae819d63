"""A few seconds of the mixed load of benchmarks/service_load.py (which runs 32 clients for
60 s and reports latency): no answers but the designed ones, memory within budget."""

from __future__ import annotations

import httpx
import pytest
from load import OCTET, Load, rss_mb
from service_client import floor_and_box, scene_body

CACHE_MB, RESULTS_MB, UPLOADS_MB = 64, 32, 64
WORKING_MB = 256  # the renders' and requests' arrays in flight
BASELINE_SLACK_MB = 64  # what the first requests add to the idle process (allocator, caches)


@pytest.mark.slow  # a few seconds of load by design
def test_mixed_load_gets_only_designed_answers_within_the_memory_budget(start_service) -> None:
    svc = start_service("--cache-mb", str(CACHE_MB), "--results-mb", str(RESULTS_MB),
                        "--uploads-mb", str(UPLOADS_MB))
    v, i = floor_and_box()
    with httpx.Client(base_url=svc.url, headers=svc.auth, timeout=60) as client:
        up = client.post("/v1/scenes", params={"vertices": len(v), "triangles": len(i)},
                         content=scene_body(v, i), headers=OCTET)
        assert up.status_code == 201, up.text
    load = Load(svc.url, svc.auth, up.json()["scene_id"], svc.proc.pid)
    idle = rss_mb(svc.proc.pid)
    report = load.run(clients=16, seconds=4.0)
    assert report.errors == []
    kinds = {kind for (kind, status) in report.statuses if status < 400 or kind == "hostile"}
    assert {"health", "head", "etag", "upload", "bvh", "ao", "job", "hostile"} <= kinds
    budget = idle + BASELINE_SLACK_MB + CACHE_MB + RESULTS_MB + UPLOADS_MB + WORKING_MB
    assert max(report.rss_mb) < budget, (max(report.rss_mb), budget)
    assert svc.proc.poll() is None
