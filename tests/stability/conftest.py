"""Shared settings for the stability suite: a deterministic hypothesis profile and the
real-service fixtures of tests/backend (a `scenesort serve` process per session)."""

from __future__ import annotations

import os

from hypothesis import HealthCheck, settings

# The service fixtures live in tests/backend/service_client.py; importing them here makes them
# available to this folder's tests without a second copy of the launcher.
from tests.backend.service_client import api, service, start_service  # noqa: F401
from tests.devices import device, pytest_configure, pytest_generate_tests  # noqa: F401

# CI runs a fixed, derandomized set of examples so a failure reproduces on every run;
# SCENESORT_HYPOTHESIS_EXAMPLES=2000 (say) explores further on a developer's machine.
settings.register_profile(
    "stability",
    max_examples=int(os.environ.get("SCENESORT_HYPOTHESIS_EXAMPLES", "60")),
    deadline=None,  # the first example pays Warp's module load
    derandomize="SCENESORT_HYPOTHESIS_EXAMPLES" not in os.environ,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
