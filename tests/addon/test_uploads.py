"""Uploads that the user stops: the add-on's client sends a body in chunks and asks
between them whether to go on; a stopped upload ends the request at once and leaves the
service healthy and without the scene (a real service, the add-on's own)."""

from __future__ import annotations

import time
from collections.abc import Iterator

import bpy
import numpy as np
import pytest

import addon
from addon import client, connection, prefs, tasks


@pytest.fixture(scope="module")
def service() -> Iterator[client.Client]:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon.register()
    prefs.preferences(bpy.context).start_on_render = True
    try:
        task = tasks.Task(lambda t: connection.connect(t, prefs.target(bpy.context)))
        yield task.run().client
    finally:
        addon.unregister()


def test_a_stopped_upload_ends_within_a_chunk(service) -> None:
    triangles = 3_000_000  # a 3M-triangle scene: 72 MB
    vertices = np.random.default_rng(0).random((triangles, 3), np.float32)
    indices = np.arange(3 * triangles, dtype=np.int32).reshape(-1, 3) % triangles
    body = vertices.tobytes() + indices.tobytes()
    scene_id = client.scene_id(triangles, triangles, body)
    asked = []

    def stop() -> bool:  # Esc after the second chunk
        asked.append(time.perf_counter())
        return len(asked) > 2

    start = time.perf_counter()
    with pytest.raises(tasks.Cancelled):
        service.upload_scene(triangles, triangles, body, stop=stop)
    assert time.perf_counter() - asked[-1] < 0.5  # back at once
    assert len(asked) == 3 < len(body) // client.UPLOAD_CHUNK
    assert time.perf_counter() - start < 5.0
    assert service.health()["status"] == "ok"  # the service took the cut short
    assert not service.has_scene(scene_id)
    # the same upload, not stopped, arrives
    answer = service.upload_scene(triangles, triangles, body, stop=lambda: False)
    assert answer["scene_id"] == scene_id and service.has_scene(scene_id)
