"""Headless Blender (the `bpy` module) with the add-on imported as the package `addon`.

`registered` gives each test a fresh empty scene with the add-on registered, and
unregisters it afterwards (which also stops any service it started). Helpers:
tests/addon/blender_scenes.py.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator

import bpy
import pytest
from blender_scenes import REPO

if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import addon  # noqa: E402 - needs the repo root on sys.path


@pytest.fixture(scope="session", autouse=True)
def blender_config(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """Blender's user config folder (the add-on's token file lives there) in a temporary
    folder: no test writes into the developer's own Blender config."""
    before = os.environ.get("BLENDER_USER_CONFIG")
    os.environ["BLENDER_USER_CONFIG"] = str(tmp_path_factory.mktemp("blender-config"))
    yield
    if before is None:
        os.environ.pop("BLENDER_USER_CONFIG")
    else:
        os.environ["BLENDER_USER_CONFIG"] = before


@pytest.fixture
def registered() -> Iterator[bpy.types.Scene]:
    """An empty scene (factory settings, no objects) with the add-on registered."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon.register()
    try:
        yield bpy.context.scene
    finally:
        addon.unregister()
