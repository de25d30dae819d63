"""AO as the service runs it: the settings of a request or a job (`AoParams`), AO on explicit
rays, and the engine's shading arguments of a scene the service holds."""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from scenesort.backend.wire.binary import InstanceScene, SceneArrays
from scenesort.backend.work.stop import StopSignal


@dataclass(frozen=True)
class AoParams:
    """AO settings shared by the explicit-ray route and camera jobs."""

    spp: int = 16
    distance: float | None = None
    seed: int = 0
    target_error: float | None = None
    max_pixel_error: float | None = None
    engine: Literal["bvh", "dacrt"] = "bvh"
    threads: int | None = None  # host threads (None: all); results do not depend on it
    denoise: bool = False  # camera jobs only: OIDN on the image

    @property
    def adaptive(self) -> bool:
        return self.target_error is not None or self.max_pixel_error is not None

    def kwargs(self) -> dict[str, Any]:
        """Keyword arguments for `kernels.ambient_occlusion` / `kernels.render_ao`."""
        out: dict[str, Any] = {"spp": self.spp, "seed": self.seed}
        if self.distance is not None:
            out["distance"] = self.distance
        if self.target_error is not None:
            out["target_error"] = self.target_error
        if self.max_pixel_error is not None:
            out["max_pixel_error"] = self.max_pixel_error
        out["engine"] = self.engine
        if self.threads is not None:
            out["threads"] = self.threads
        return out


def ao_params(request: Any, threads: int | None = None) -> AoParams:
    """The AO settings of a job request (models.JobRequest, or a frame of a bundle)."""
    return AoParams(
        spp=request.spp,
        distance=request.distance,
        seed=request.seed,
        target_error=request.target_error,
        max_pixel_error=request.max_pixel_error,
        engine=request.engine,
        threads=threads,
        denoise=request.denoise,
    )


def ambient_occlusion(
    bvh: Any, scene: Any, origins: np.ndarray, directions: np.ndarray, params: AoParams,
    signal: StopSignal,
) -> tuple[np.ndarray, dict[str, float]]:
    """AO for explicit rays, exactly `kernels.ambient_occlusion` (which is
    `render_ao(...).ao`) with the scene's normals, with the engine's phase timings;
    `signal` is checked between the engine's rounds (it raises Stopped there)."""
    from scenesort import kernels

    result = kernels.render_ao(
        bvh, origins, directions, progress=lambda *_: signal.check(), **params.kwargs(),
        **shading(scene),
    )
    return np.asarray(result.ao, dtype=np.float32), dict(result.timings_ms)


# An instance list's arguments are made once: the engine keeps its device copy of the
# normals for the same objects, so every render of the list must pass the same ones.
_INSTANCE_SHADING: weakref.WeakKeyDictionary[InstanceScene, dict[str, object]] = (
    weakref.WeakKeyDictionary())


def shading(scene: SceneArrays | InstanceScene) -> dict[str, object]:
    """The engine's keyword arguments for the scene's normals and terminator offsets (none:
    flat shading). An instance list passes each mesh's normals in object space and each
    instance's offset."""
    if isinstance(scene, SceneArrays):
        out: dict[str, object] = {}
        if scene.normals is not None:
            out["normals"] = scene.normals
        if scene.terminator_offsets is not None:
            out["terminator_offset"] = scene.terminator_offsets
        return out
    found = _INSTANCE_SHADING.get(scene)
    if found is None:
        found = _INSTANCE_SHADING[scene] = _instance_shading(scene)
    return found


def _instance_shading(scene: InstanceScene) -> dict[str, object]:
    from scenesort.kernels.render.ao import DEFAULT_TERMINATOR_OFFSET

    normals = [m.normals for m in scene.meshes]
    if all(n is None for n in normals):
        return {}
    out: dict[str, object] = {"normals": normals}
    offsets = [m.terminator_offsets for m in scene.meshes]
    if any(o is not None for o in offsets):
        per_mesh = np.array([DEFAULT_TERMINATOR_OFFSET if o is None else o[0]
                             for o in offsets], np.float32)
        out["terminator_offset"] = per_mesh[scene.mesh_index]
    return out
