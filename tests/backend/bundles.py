"""Frame bundles written from numpy, for the backend's tests: the format of docs/api.md
("Frame bundles") written independently of the add-on's writer."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from backend import wire


def mesh_body(vertices: np.ndarray, indices: np.ndarray) -> bytes:
    return vertices.astype("<f4").tobytes() + indices.astype("<i4").tobytes()


def mesh_id(vertices: np.ndarray, indices: np.ndarray) -> str:
    return wire.scene_hash(len(vertices), len(indices), mesh_body(vertices, indices))


def instance_body(ids: list[str], mesh_index: list[int], transforms: np.ndarray) -> bytes:
    return ("".join(ids).encode() + np.asarray(mesh_index, "<i4").tobytes()
            + np.asarray(transforms, "<f4").tobytes())


def look_at_camera(position: tuple[float, float, float], width: int = 24,
                   height: int = 18) -> dict[str, Any]:
    """A camera wire form at `position` looking down -z (Blender's camera axes)."""
    matrix = np.eye(4)
    matrix[:3, 3] = position
    return {"matrix_world": matrix.tolist(), "width": width, "height": height,
            "clip_start": 0.01, "clip_end": 100.0}


@dataclass
class BundleWriter:
    """Frames added one by one, then `write(root)`."""

    settings: dict[str, Any] = field(default_factory=lambda: {"spp": 4, "seed": 1,
                                                              "distance": 1.0})
    meshes: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    frames: dict[int, tuple[dict[str, Any], list[str], list[int], np.ndarray]] = field(
        default_factory=dict)

    def frame(self, number: int, camera: dict[str, Any],
              instances: list[tuple[tuple[np.ndarray, np.ndarray], np.ndarray]]) -> None:
        """Frame `number`: `instances` as ((vertices, indices), 3x4 transform) pairs."""
        ids: list[str] = []
        index: list[int] = []
        for mesh, _ in instances:
            name = mesh_id(*mesh)
            self.meshes[name] = mesh
            if name not in ids:
                ids.append(name)
            index.append(ids.index(name))
        transforms = np.array([t for _, t in instances], np.float32)
        self.frames[number] = (camera, ids, index, transforms)

    def write(self, root: Path) -> Path:
        (root / "meshes").mkdir(parents=True, exist_ok=True)
        (root / "frames").mkdir(exist_ok=True)
        for name, (v, i) in self.meshes.items():
            (root / "meshes" / f"{name}.bin").write_bytes(mesh_body(v, i))
        for number, (camera, ids, index, transforms) in self.frames.items():
            stem = root / "frames" / f"{number:06d}"
            stem.with_suffix(".bin").write_bytes(instance_body(ids, index, transforms))
            record = {"frame": number, "camera": camera, "window": None,
                      "pixel_aspect": [1.0, 1.0], "meshes": len(ids), "instances": len(index)}
            stem.with_suffix(".json").write_text(json.dumps(record))
        manifest = {
            "format": "scenesort-frame-bundle", "version": 1, "frames": list(self.frames),
            "settings": self.settings,
            "meshes": {name: {"vertices": len(v), "triangles": len(i), "normals": False,
                              "terminator_offsets": False}
                       for name, (v, i) in self.meshes.items()},
        }
        (root / "manifest.json").write_text(json.dumps(manifest))
        return root
