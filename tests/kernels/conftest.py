from __future__ import annotations

import pytest
from scenesort.backend.render.scenes import shared_scene as load_shared_scene
from scenesort.backend.render.scenes import shared_scenes_dir

from tests.devices import device, pytest_configure, pytest_generate_tests  # noqa: F401


@pytest.fixture(scope="session")
def shared_scene():
    """Loader for the real meshes in ../shared/scenes (present on every project machine)."""
    if shared_scenes_dir() is None:
        pytest.fail("../shared/scenes not found: set SCENESORT_SCENES to the scenes folder")
    cache = {}

    def load(name: str):
        if name not in cache:
            cache[name] = load_shared_scene(name)
        return cache[name]

    return load
