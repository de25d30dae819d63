"""Cameras for the backend's bundle tests (bundles themselves: backend.bundle.BundleWriter,
a writer apart from the add-on's, so the add-on's is tested against it)."""

from __future__ import annotations

from typing import Any

import numpy as np


def look_at_camera(position: tuple[float, float, float], width: int = 24,
                   height: int = 18) -> dict[str, Any]:
    """A camera wire form at `position` looking down -z (Blender's camera axes)."""
    matrix = np.eye(4)
    matrix[:3, 3] = position
    return {"matrix_world": matrix.tolist(), "width": width, "height": height,
            "clip_start": 0.01, "clip_end": 100.0}


