"""Scenes: triangle meshes from files, the shared test scenes, and the built-in default scene.

A `Scene` is float32 vertices (N,3), int32 triangle indices (M,3) and a `Camera`.
The shared scenes live in `../shared/scenes` (or `$SCENESORT_SCENES`) with their
cameras in `scenes.json`; the default scene is generated here, deterministically,
so that a fresh clone renders something without any file.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scenesort.kernels import Camera

SCENES_ENV = "SCENESORT_SCENES"
DEFAULT_WIDTH, DEFAULT_HEIGHT = 640, 480


@dataclass(frozen=True, eq=False)
class Scene:
    """A triangle mesh in world space and the camera that frames it."""

    name: str
    vertices: np.ndarray  # (N,3) float32
    indices: np.ndarray  # (M,3) int32, each in [0, N)
    camera: Camera

    @property
    def triangles(self) -> int:
        return int(self.indices.shape[0])


# --- files -----------------------------------------------------------------------------


def load_mesh(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (N,3) float32 and triangles (M,3) int32 of a mesh file (PLY, OBJ, STL, ...).

    Every face is kept as stored, duplicated and zero-area ones included (trimesh with
    `process=False`; Blender's PLY importer, by contrast, drops duplicates).
    """
    import trimesh  # imported here: only file loading needs it

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"mesh path {str(path)!r} is not a file")
    try:
        mesh = trimesh.load(path, process=False, force="mesh")
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise ValueError(f"cannot read mesh {str(path)!r}: {exc}") from exc
    faces = np.asarray(getattr(mesh, "faces", np.empty((0, 3))))
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] == 0:
        raise ValueError(f"mesh {str(path)!r} has no triangles (faces shape {faces.shape})")
    vertices = np.ascontiguousarray(mesh.vertices, dtype=np.float32)
    if not np.all(np.isfinite(vertices)):
        raise ValueError(f"mesh {str(path)!r} has non-finite vertex coordinates")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError(f"mesh {str(path)!r} has face indices outside 0..{len(vertices) - 1}")
    return vertices, np.ascontiguousarray(faces, dtype=np.int32)


def shared_scenes_dir() -> Path | None:
    """The shared scenes folder: `$SCENESORT_SCENES`, else `<repo>/../shared/scenes`.

    None when the default folder does not exist (a fresh clone has none); a set but
    wrong `$SCENESORT_SCENES` is an error rather than silently ignored.
    """
    env = os.environ.get(SCENES_ENV)
    if env:
        path = Path(env)
        if not (path / "scenes.json").is_file():
            raise ValueError(f"${SCENES_ENV}={env!r} must be a folder holding scenes.json")
        return path
    path = Path(__file__).resolve().parents[3] / "shared" / "scenes"  # beside the checkout
    return path if (path / "scenes.json").is_file() else None


def shared_scene_infos() -> dict[str, dict[str, Any]]:
    """scenes.json entries by name (empty when there is no shared folder)."""
    folder = shared_scenes_dir()
    if folder is None:
        return {}
    entries = json.loads((folder / "scenes.json").read_text())
    return {entry["name"]: entry for entry in entries}


def shared_scene(name: str, width: int = DEFAULT_WIDTH, height: int = DEFAULT_HEIGHT) -> Scene:
    """A shared scene by name (e.g. "sponza"), with its scenes.json camera at width x height."""
    folder = shared_scenes_dir()
    if folder is None:
        raise ValueError(
            f"no shared scenes folder: set ${SCENES_ENV} to the folder holding scenes.json"
        )
    infos = shared_scene_infos()
    if name not in infos:
        raise ValueError(f"unknown scene {name!r}; shared scenes are {sorted(infos)}")
    info = infos[name]
    vertices, indices = load_mesh(folder / info["file"])
    cam = info["camera"]
    camera = Camera.look_at(
        cam["position"], cam["look_at"], cam["up"], cam["fov_y_deg"], width, height
    )
    return Scene(name, vertices, indices, camera)


# --- what `scenesort render` and `scenesort bench` take: a file, a name or nothing ------


def load_scene(scene: str | None, width: int | None, height: int | None) -> Scene:
    """The built-in scene, a shared scene by name, or a mesh file with a framing camera."""
    w = width or DEFAULT_WIDTH
    h = height or DEFAULT_HEIGHT
    if scene is None:
        return default_scene(w, h)
    path = Path(scene)
    if path.suffix or path.exists():
        vertices, indices = load_mesh(path)
        return Scene(path.stem, vertices, indices, framing_camera(vertices, w, h))
    return shared_scene(scene, w, h)


def framing_camera(vertices: np.ndarray, width: int, height: int) -> Camera:
    """A 35-degree pinhole camera on the +Y+Z diagonal that fits the mesh's bounding
    sphere with a 10% margin (like the shared scenes' object cameras)."""
    lo, hi = vertices.min(axis=0).astype(float), vertices.max(axis=0).astype(float)
    centre = 0.5 * (lo + hi)
    radius = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-6)
    fov = 35.0
    dist = 1.1 * radius / np.sin(np.radians(fov) / 2.0)
    view = np.array([0.5, 0.4, 1.0]) / np.linalg.norm([0.5, 0.4, 1.0])
    return Camera.look_at(
        centre + dist * view, centre, (0, 1, 0), fov, width, height, clip_start=0.0, clip_end=1e10
    )


def load_camera(path: Path, width: int, height: int) -> Camera:
    """A camera from JSON: the Camera wire form, or a scenes.json look-at description."""
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"--camera {str(path)!r} is not a readable JSON file: {exc}") from exc
    if isinstance(data, dict) and "matrix_world" in data:
        return Camera.from_dict(data)
    keys = ("position", "look_at", "up", "fov_y_deg")
    if not isinstance(data, dict) or any(k not in data for k in keys):
        raise ValueError(f"--camera must hold a Camera (matrix_world, ...) or the keys {keys}")
    return Camera.look_at(
        data["position"], data["look_at"], data["up"], data["fov_y_deg"], width, height
    )


# --- the built-in default scene ----------------------------------------------------------
# A room corner (floor, back and left walls) holding an icosphere, a torus lying flat and
# a stack of boxes, all resting on the floor so that AO shows in corners and contacts.
# Z is up (Blender's convention). 109,312 triangles.


def _grid(origin, du, dv, nu: int, nv: int) -> tuple[np.ndarray, np.ndarray]:
    """A flat quad split into nu x nv cells of two triangles; normal along du x dv."""
    a, b = np.meshgrid(np.arange(nu + 1) / nu, np.arange(nv + 1) / nv, indexing="ij")
    v = np.asarray(origin, float) + a[..., None] * np.asarray(du) + b[..., None] * np.asarray(dv)
    i = np.arange((nu + 1) * (nv + 1)).reshape(nu + 1, nv + 1)
    p00, p10, p01, p11 = i[:-1, :-1], i[1:, :-1], i[:-1, 1:], i[1:, 1:]
    tris = np.concatenate([np.stack([p00, p10, p11], -1), np.stack([p00, p11, p01], -1)])
    return v.reshape(-1, 3), tris.reshape(-1, 3)


def _box(centre, size, yaw_deg: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """An axis-aligned box turned about Z, each face an n x n grid, normals outward."""
    parts = []
    for axis in range(3):
        u, w = np.eye(3)[(axis + 1) % 3], np.eye(3)[(axis + 2) % 3]
        for sign in (-1.0, 1.0):
            normal = sign * np.eye(3)[axis]
            du, dv = (u, w) if sign > 0 else (w, u)  # du x dv points along `normal`
            parts.append(_grid(0.5 * (normal - du - dv), du, dv, n, n))
    v, t = _merge(parts)
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return (v * np.asarray(size)) @ rot.T + np.asarray(centre), t


def _icosphere(centre, radius: float, levels: int) -> tuple[np.ndarray, np.ndarray]:
    """An icosahedron subdivided `levels` times (20 * 4**levels triangles), on a sphere."""
    g = (1.0 + math.sqrt(5.0)) / 2.0
    v = np.array(
        [[-1, g, 0], [1, g, 0], [-1, -g, 0], [1, -g, 0], [0, -1, g], [0, 1, g],
         [0, -1, -g], [0, 1, -g], [g, 0, -1], [g, 0, 1], [-g, 0, -1], [-g, 0, 1]], float
    )  # fmt: skip
    t = np.array(
        [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
         [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
         [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]
    )  # fmt: skip
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(levels):
        edges = np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)
        unique, inverse = np.unique(edges, axis=0, return_inverse=True)
        mid = v[unique[:, 0]] + v[unique[:, 1]]
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = (inverse.reshape(3, -1) + len(v)).T  # midpoints of edges 01, 12, 20
        v = np.concatenate([v, mid])
        t = np.concatenate(
            [
                np.stack([t[:, 0], m[:, 0], m[:, 2]], 1),
                np.stack([t[:, 1], m[:, 1], m[:, 0]], 1),
                np.stack([t[:, 2], m[:, 2], m[:, 1]], 1),
                m,
            ]
        )
    return v * radius + np.asarray(centre), t


def _torus(centre, major: float, minor: float, nu: int, nv: int) -> tuple[np.ndarray, np.ndarray]:
    """A torus around Z (lying flat), nu segments around and nv around the tube."""
    a, b = np.meshgrid(np.arange(nu) * 2 * np.pi / nu, np.arange(nv) * 2 * np.pi / nv,
                       indexing="ij")  # fmt: skip
    ring = major + minor * np.cos(b)
    v = np.stack([ring * np.cos(a), ring * np.sin(a), minor * np.sin(b)], -1).reshape(-1, 3)
    i = np.arange(nu * nv).reshape(nu, nv)
    p00, p10 = i, np.roll(i, -1, axis=0)
    p01, p11 = np.roll(p00, -1, axis=1), np.roll(p10, -1, axis=1)
    t = np.concatenate([np.stack([p00, p10, p11], -1), np.stack([p00, p11, p01], -1)])
    return v + np.asarray(centre), t.reshape(-1, 3)


def _merge(parts: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Concatenate meshes, offsetting each one's indices past the previous vertices."""
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    vertices = np.concatenate([v for v, _ in parts])
    indices = np.concatenate([t + o for (_, t), o in zip(parts, offsets, strict=True)])
    return vertices, indices


def default_scene(width: int = DEFAULT_WIDTH, height: int = DEFAULT_HEIGHT) -> Scene:
    """The built-in scene: a room corner with a sphere, a torus and boxes (109,312 triangles)."""
    lo, hi, wall = -5.0, 9.0, 5.0  # walls stand at x = lo and y = -lo; floor reaches hi
    size = hi - lo
    parts = [
        _grid((lo, -hi, 0), (size, 0, 0), (0, size, 0), 128, 128),  # floor
        _grid((lo, -lo, 0), (size, 0, 0), (0, 0, wall), 128, 48),  # back wall
        _grid((lo, -hi, 0), (0, size, 0), (0, 0, wall), 128, 48),  # left wall
        _icosphere((0.2, 2.3, 1.2), 1.2, 5),  # touches the floor at one point
        _torus((1.9, -1.0, 0.4), 1.1, 0.4, 192, 64),  # lies on the floor
        _box((-4.35, 4.35, 0.6), (1.2, 1.2, 1.2), 0.0, 12),  # in the corner, 5 cm off both walls
        _box((-4.35, 4.35, 1.55), (0.7, 0.7, 0.7), 30.0, 12),  # stacked on it, turned
        _box((2.6, 3.0, 0.9), (1.0, 1.6, 1.8), -20.0, 12),  # near the back wall
        _box((-2.6, -2.4, 0.35), (0.7, 0.7, 0.7), 45.0, 12),
    ]
    vertices, indices = _merge(parts)
    camera = Camera.look_at((6.0, -6.0, 4.5), (-1.0, 1.2, 0.9), (0, 0, 1), 50.0, width, height)
    return Scene(
        "default",
        np.ascontiguousarray(vertices, dtype=np.float32),
        np.ascontiguousarray(indices, dtype=np.int32),
        camera,
    )
