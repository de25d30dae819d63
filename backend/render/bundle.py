"""Frame bundles: an animation on disk, as the add-on's File > Export > scenesort animation
writes it and `scenesort render-frames` reads it (docs/api.md, "Frame bundles").

A bundle is a directory:

    manifest.json          {"format": "scenesort-frame-bundle", "version": 1,
                            "frames": [1, 2, ...], "settings": {spp, seed, distance, ...},
                            "meshes": {mesh_id: {"vertices": V, "triangles": T,
                                                 "normals": bool, "terminator_offsets": bool}}}
    meshes/<mesh_id>.bin   a mesh in its own space, the body of PUT /v1/meshes/{mesh_id};
                           written once per distinct content (a deformed mesh is a new id
                           in the frames where it changed)
    frames/<frame>.json    {"frame": F, "camera": {...}, "window": null | {...},
                            "pixel_aspect": [x, y], "meshes": K, "instances": N,
                            "visibility": bool (optional: the list ends with masks)}
    frames/<frame>.bin     the frame's instance list, the body of POST /v1/instance-scenes

`<frame>` is the frame number as `%06d`. The settings and a frame's view are the fields of
a service job (POST /v1/jobs without scene_id), validated by the same model and checked
together as AoOptions; a setting left out takes the job's default (AoOptions'). Meshes are
read when a frame first needs them, and their ids are checked against their bytes.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError
from scenesort.backend.render.engine import count_degenerate
from scenesort.backend.wire import binary as wire
from scenesort.backend.wire.models import JobRequest
from scenesort.backend.wire.problems import ApiError

from scenesort.ao_options import AoOptions

FORMAT = "scenesort-frame-bundle"
VERSION = 1
MANIFEST = "manifest.json"


class BundleError(ValueError):
    """A bundle that cannot be read; the message names the file and the field."""


def mesh_path(root: Path, mesh_id: str) -> Path:
    return root / "meshes" / f"{mesh_id}.bin"


def frame_stem(root: Path, frame: int) -> Path:
    """The frame's files without their suffix (.json, .bin)."""
    return root / "frames" / f"{frame:06d}"


@dataclass(frozen=True)
class Frame:
    """One frame: its number, the job fields (view and settings), its instance list and its
    AO settings checked together (`JobRequest.options()`)."""

    number: int
    request: JobRequest  # scene_id is the instance list's id
    instances: wire.InstanceList
    options: AoOptions


def _load_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except OSError as exc:
        raise BundleError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    except json.JSONDecodeError as exc:
        raise BundleError(f"{path}: not valid JSON ({exc})") from None


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as exc:
        raise BundleError(f"{path}: cannot be read ({exc.strerror or exc})") from None


def _api(path: Path, exc: ApiError) -> BundleError:
    return BundleError(f"{path}: {exc.parameter}: {exc.message} ({exc.fix})")


def _count(path: Path, data: dict, key: str) -> int:
    value = data.get(key)
    if not isinstance(value, int) or isinstance(value, bool) or value < 1:
        raise BundleError(f"{path}: {key!r} must be an integer >= 1, got {value!r}")
    return value


class Bundle:
    """A bundle opened for reading: its manifest read and checked, everything else lazily."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        path = self.root / MANIFEST
        manifest = _load_json(path)
        if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
            raise BundleError(f"{path}: not a scenesort frame bundle (format must be {FORMAT!r})")
        if manifest.get("version") != VERSION:
            raise BundleError(
                f"{path}: format version {manifest.get('version')!r}; this scenesort reads "
                f"version {VERSION} (export the animation again with this add-on)"
            )
        frames = manifest.get("frames")
        if not isinstance(frames, list) or not frames or not all(
                isinstance(f, int) and not isinstance(f, bool) for f in frames):
            raise BundleError(f"{path}: 'frames' must be a non-empty list of frame numbers")
        if len(set(frames)) != len(frames):
            raise BundleError(f"{path}: 'frames' lists a frame twice")
        self.frames: tuple[int, ...] = tuple(frames)
        settings, meshes = manifest.get("settings"), manifest.get("meshes")
        if not isinstance(settings, dict):
            raise BundleError(f"{path}: 'settings' must be an object of job fields")
        if not isinstance(meshes, dict):
            raise BundleError(f"{path}: 'meshes' must be an object keyed by mesh id")
        self.settings: dict[str, Any] = settings
        self.mesh_info: dict[str, dict[str, Any]] = meshes

    def mesh(self, mesh_id: str) -> wire.SceneArrays:
        """The mesh `mesh_id`, read, validated and checked against its id."""
        info = self.mesh_info.get(mesh_id)
        path = mesh_path(self.root, mesh_id)
        if not isinstance(info, dict):
            raise BundleError(f"{self.root / MANIFEST}: 'meshes' has no mesh {mesh_id}")
        vertices, triangles = _count(path, info, "vertices"), _count(path, info, "triangles")
        blocks = {k: bool(info.get(k, False)) for k in ("normals", "terminator_offsets")}
        body = _read_bytes(path)
        found = wire.scene_hash(vertices, triangles, body)
        if found != mesh_id:
            raise BundleError(f"{path}: its content hashes to {found}, not its name {mesh_id}")
        try:
            return wire.decode_scene(body, vertices, triangles, mesh_id, **blocks,
                                     count_degenerate=count_degenerate)
        except ApiError as exc:
            raise _api(path, exc) from None

    def frame(self, number: int) -> Frame:
        """Frame `number`'s view, settings and instance list."""
        if number not in self.frames:
            raise BundleError(f"frame {number} is not in the bundle (frames "
                              f"{self.frames[0]}..{self.frames[-1]}, {len(self.frames)} in all)")
        stem = frame_stem(self.root, number)
        path = stem.with_suffix(".json")
        data = _load_json(path)
        if not isinstance(data, dict):
            raise BundleError(f"{path}: must be a JSON object")
        meshes, instances = _count(path, data, "meshes"), _count(path, data, "instances")
        masks = data.get("visibility", False)
        if not isinstance(masks, bool):
            raise BundleError(f"{path}: visibility must be true or false, got {masks!r}")
        body_path = stem.with_suffix(".bin")
        try:
            listing = wire.decode_instances(_read_bytes(body_path), meshes, instances, masks)
        except ApiError as exc:
            raise _api(body_path, exc) from None
        view = {k: data[k] for k in ("camera", "window", "pixel_aspect") if k in data}
        try:
            request = JobRequest(scene_id=listing.scene_id, **view, **self.settings)
        except ValidationError as exc:
            first = exc.errors()[0]
            where = ".".join(str(p) for p in first.get("loc", ()))
            raise BundleError(f"{path} (with the manifest's settings): {where}: "
                              f"{first.get('msg')}") from None
        try:
            options = request.options()
        except ApiError as exc:
            raise _api(self.root / MANIFEST, exc) from None
        return Frame(number, request, listing, options)


def read_bundle(path: str | Path) -> Bundle:
    """Open the bundle at `path` (a directory holding manifest.json)."""
    return Bundle(Path(path))


# --- writing ---------------------------------------------------------------------------


def mesh_body(vertices: np.ndarray, indices: np.ndarray) -> bytes:
    """A mesh without normals in the PUT /v1/meshes layout."""
    return vertices.astype("<f4").tobytes() + indices.astype("<i4").tobytes()


def mesh_id(vertices: np.ndarray, indices: np.ndarray) -> str:
    """That mesh's content hash: its id in a bundle and in the service."""
    return wire.scene_hash(len(vertices), len(indices), mesh_body(vertices, indices))


def instance_body(ids: list[str], mesh_index: list[int], transforms: np.ndarray,
                  visibility: Any = None) -> bytes:
    """An instance list in the POST /v1/instance-scenes layout (with `visibility`, the
    per-instance uint8 masks of `visibility=true`)."""
    masks = b"" if visibility is None else np.asarray(visibility, np.uint8).tobytes()
    return ("".join(ids).encode() + np.asarray(mesh_index, "<i4").tobytes()
            + np.asarray(transforms, "<f4").tobytes() + masks)


@dataclass
class BundleWriter:
    """A bundle from numpy, without Blender (pipelines, tests, benchmarks): frames added one
    by one, then `write(root)`. Meshes without normals; the add-on writes its own.
    `settings`: job fields (spp, seed, ...); those left out take the job's defaults."""

    settings: dict[str, Any] = field(default_factory=dict)
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
            mesh_path(root, name).write_bytes(mesh_body(v, i))
        for number, (camera, ids, index, transforms) in self.frames.items():
            stem = frame_stem(root, number)
            stem.with_suffix(".bin").write_bytes(instance_body(ids, index, transforms))
            record = {"frame": number, "camera": camera, "window": None,
                      "pixel_aspect": [1.0, 1.0], "meshes": len(ids), "instances": len(index)}
            stem.with_suffix(".json").write_text(json.dumps(record))
        manifest = {
            "format": FORMAT, "version": VERSION, "frames": list(self.frames),
            "settings": self.settings,
            "meshes": {name: {"vertices": len(v), "triangles": len(i), "normals": False,
                              "terminator_offsets": False}
                       for name, (v, i) in self.meshes.items()},
        }
        (root / MANIFEST).write_text(json.dumps(manifest))
        return root
