"""AO as the service runs it: AO on explicit rays, and the engine's shading arguments of a
scene the service holds. (A request's settings are `AoOptions`: wire/models.py.)"""

from __future__ import annotations

import weakref
from typing import Any

import numpy as np
from scenesort.backend.wire.binary import InstanceScene, SceneArrays
from scenesort.backend.work.stop import StopSignal

from scenesort.ao_options import DEFAULT_TERMINATOR_OFFSET, AoOptions


def ambient_occlusion(
    bvh: Any, scene: Any, origins: np.ndarray, directions: np.ndarray, options: AoOptions,
    signal: StopSignal,
) -> tuple[np.ndarray, dict[str, float]]:
    """AO for explicit rays, exactly `kernels.ambient_occlusion` (which is
    `render_ao(...).ao`) with the scene's normals, with the engine's phase timings;
    `signal` is checked between the engine's rounds (it raises Stopped there)."""
    from scenesort import kernels

    result = kernels.render_ao(bvh, origins, directions, options,
                               progress=lambda *_: signal.check(), **shading(scene))
    return np.asarray(result.ao, dtype=np.float32), result.timings_ms.to_dict()


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
