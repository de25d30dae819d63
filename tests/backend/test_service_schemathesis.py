"""Property-based requests generated from /openapi.json (schemathesis), sent with the
service's token (the authenticated API): never a 5xx.

Bounded in count (max_examples per operation and generation mode) and time (a per-request timeout
and a total budget after which no more requests are sent). Half of the generated
scene ids are swapped for a scene the service holds, and AO bodies are made to match
small ray counts, so that the BVH and AO routes are reached, not only their 404s.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.errors import Unsatisfiable

pytestmark = pytest.mark.slow  # 40 generated requests per operation, twice: ~17 s

EXAMPLES_PER_OPERATION = 40
BUDGET_S = 120.0
MAX_RAYS = 64  # AO requests on the known scene carry at most this many rays


@pytest.fixture(scope="module")
def scene_id(api, box_scene) -> str:
    response = api.upload(*box_scene)
    assert response.status_code in (200, 201), response.text
    return response.json()["scene_id"]


def aim_at_scene(case, use_known: bool, scene_id: str, rng_seed: int):
    """Point path scene ids at the known scene; give AO a few rays and a matching body."""
    if use_known and "scene_id" in (case.path_parameters or {}):
        case.path_parameters["scene_id"] = scene_id
        if case.path.endswith("/ao") and isinstance(case.query, dict):
            rays = case.query["rays"] = rng_seed % MAX_RAYS + 1
            rng = np.random.default_rng(rng_seed)
            data = rng.uniform(-1, 1, (rays, 6)).astype("<f4")
            data[:, 4] -= 2.0  # nonzero directions, mostly towards the floor
            case.body = data.tobytes()
    return case


@pytest.mark.parametrize("mode", ["positive", "negative"])
def test_generated_requests_never_get_a_5xx(service, scene_id, mode) -> None:
    schema = schemathesis.openapi.from_url(f"{service.url}/openapi.json", headers=service.auth)
    deadline = time.monotonic() + BUDGET_S
    seen: set[tuple[str, str, int]] = set()
    operations = [result.ok() for result in schema.get_all_operations()]

    for operation in operations:  # each operation gets its own bounded run
        strategy = operation.as_strategy(generation_mode=schemathesis.GenerationMode(mode))

        @settings(
            max_examples=EXAMPLES_PER_OPERATION,
            deadline=None,
            database=None,
            derandomize=True,
            suppress_health_check=list(HealthCheck),
        )
        @given(case=strategy, use_known=st.booleans(), seed=st.integers(0, 2**16))
        def check(case, use_known, seed) -> None:
            if time.monotonic() > deadline:
                return  # budget spent: stop sending, keep what was checked
            case = aim_at_scene(case, use_known, scene_id, seed)
            response = case.call(base_url=service.url, headers=service.auth, timeout=60)
            seen.add((case.method, case.path, response.status_code))
            assert response.status_code < 500, (case.method, case.path, response.text[:500])

        try:
            check()
        except Unsatisfiable:  # e.g. no invalid request exists for GET /v1/health
            assert mode == "negative"

    if mode == "positive":
        exercised = {(m, p) for m, p, _ in seen}
        assert exercised == {(op.method.upper(), op.path) for op in operations}
    assert service.proc.poll() is None
    if mode == "positive":  # valid requests on the known scene got through to the engine
        ok = {p.rsplit("/", 1)[-1] for m, p, status in seen if status == 200}
        assert {"bvh", "ao"} <= ok, sorted(seen)
