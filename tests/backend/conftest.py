"""Fixtures: `start_service(*args)` starts a real service (stopped at session end),
`service` is one shared instance, `api` a client of it (all three from
tests/backend/service_client.py); `inproc`, the service in this process, and `gate`, its
engine held until the test releases it (tests/backend/gated.py); `box_scene` and `make_rays`.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from gated import gate, inproc  # noqa: F401
from service_client import api, floor_and_box, rays_towards_floor, service, start_service  # noqa: F401


@pytest.fixture(scope="session")
def box_scene() -> tuple[np.ndarray, np.ndarray]:
    """The small floor-and-box scene (vertices, indices)."""
    return floor_and_box()


@pytest.fixture(scope="session")
def make_rays() -> Callable[..., tuple[np.ndarray, np.ndarray]]:
    """`make_rays(count, seed=1)` -> (origins, directions) aimed at the box scene's floor."""
    return rays_towards_floor
