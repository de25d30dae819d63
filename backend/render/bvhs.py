"""BVHs by content hash, so that a frame (or a job) redoes only what changed.

The cache is a `Store` (work/store.py) keyed by content hash:

- a mesh's BVH under `bvh_key(mesh_id, method, leaf_size)`: the same mesh data under many
  objects or instances is built once;
- its topology (vertex count and indices, `SceneArrays.topology`) under
  `topology_key(...)`, naming the last mesh built with it: a deformed mesh (same topology,
  new positions) is refit from that one's BVH, and the engine's `refit_bvh` decides whether
  to rebuild anyway;
- an instance list's top level under `bvh_key(scene_id, ...)`, where the scene id is the
  list's content hash (mesh ids and transforms).

Hence the skip rules: a frame whose instance list is unchanged (only the camera moved)
builds nothing; one whose transforms changed builds only the top level; a mesh that
deformed is refit and nothing else is touched. `BuildReport` says per frame what was done.

With a camera (`visibility.View`) only the meshes of the instances that may change a pixel
are built or refit (a mesh out of view waits until it enters it), and the top level is over
those instances, kept under `culled_key` with which they are. A camera-only change that
leaves the same instances in view builds nothing; one that changes them builds the top level
(and the meshes coming into view). Nothing culled: the scene's own top level (`bvh_key`), as
without a camera.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from scenesort.backend.render.visibility import View, placement, visible
from scenesort.backend.wire import binary as wire
from scenesort.backend.work.store import Store, bvh_key, bvh_nbytes

TopLevel = Literal["built", "reused", "none"]


def topology_key(topology: str, method: str, leaf_size: int) -> str:
    """The cache key naming the last mesh with this topology whose BVH was made."""
    return f"{topology}/topology/{method}/{leaf_size}"


def culled_key(scene_id: str, method: str, leaf_size: int) -> str:
    """The cache key of an instance list's top level over the instances a camera sees
    (kept with the mask of which they are; not a `bvh_key`: AO on explicit rays, which
    takes a scene's latest BVH, must not find it)."""
    return f"{scene_id}/culled/bvh/{method}/{leaf_size}"


@dataclass
class BuildReport:
    """What a frame (or a job) did to have its BVHs: mesh ids built from scratch, refit
    from an earlier mesh of the same topology, or reused; the top level built, reused, or
    none (a single-mesh scene has no top level); the instances culled (out of the camera's
    view widened by the AO distance: not in the top level) and the meshes skipped (no
    instance in view: no BVH made or used); the device bytes of what is traced; and the
    time of each part in ms."""

    built: list[str] = field(default_factory=list)
    refit: list[str] = field(default_factory=list)
    reused: list[str] = field(default_factory=list)
    top_level: TopLevel = "none"
    culled: int = 0
    skipped: list[str] = field(default_factory=list)
    bvh_bytes: int = 0
    timings_ms: dict[str, float] = field(default_factory=dict)

    @property
    def cached(self) -> bool:
        """Whether nothing was built or refit."""
        return not self.built and not self.refit and self.top_level != "built"

    def to_dict(self) -> dict[str, Any]:
        return {"built": list(self.built), "refit": list(self.refit),
                "reused": list(self.reused), "top_level": self.top_level,
                "culled": self.culled, "skipped": list(self.skipped),
                "bvh_bytes": self.bvh_bytes, "timings_ms": dict(self.timings_ms)}

    def measure(self, name: str, fn: Callable[[], Any]) -> Any:
        start = time.perf_counter()
        out = fn()
        self.timings_ms[name] = self.timings_ms.get(name, 0.0) + 1e3 * (time.perf_counter() - start)
        return out


TOPOLOGY_DONORS = 8  # meshes remembered per topology as refit donors, newest last


def mesh_bvh(store: Store, mesh: wire.SceneArrays, method: str, leaf_size: int, device: str,
             report: BuildReport, in_use: frozenset[str] | None = None) -> Any:
    """The mesh's BVH: cached, else refit from the BVH of an earlier mesh of its topology
    (one that `in_use`, the meshes of the same instance list, does not hold), else built.
    `in_use` None: a single-mesh scene, built as the single-mesh API always has (with the
    statistics of a fresh build), and never a refit's donor."""
    from scenesort import kernels

    key = bvh_key(mesh.scene_id, method, leaf_size)
    bvh = store.get(key)
    if bvh is not None:
        report.reused.append(mesh.scene_id)
        return bvh
    topo = topology_key(mesh.topology, method, leaf_size)
    donors, donor_id = [], None
    if in_use is not None:
        donors = [d for d in store.get(topo) or [] if d != mesh.scene_id]
        donor_id = next((d for d in reversed(donors) if d not in in_use
                         and bvh_key(d, method, leaf_size) in store), None)
    if donor_id is not None:
        donor = store.get(bvh_key(donor_id, method, leaf_size))
        bvh = report.measure("refit", lambda: kernels.refit_bvh(donor, mesh.vertices))
        # The refit works in place, also when the engine's rule then rebuilds (the refit
        # tree would cost too much): the donor's BVH and its top levels are stale now.
        _forget(store, donor_id, method, leaf_size)
        donors.remove(donor_id)
        (report.refit if bvh is donor else report.built).append(mesh.scene_id)
    else:
        bvh = report.measure("build", lambda: kernels.build_bvh(
            mesh.vertices, mesh.indices, method=method, leaf_size=leaf_size, device=device))
        report.built.append(mesh.scene_id)
    store.put(key, bvh, bvh_nbytes(bvh))
    if in_use is not None:
        store.put(topo, [*donors, mesh.scene_id][-TOPOLOGY_DONORS:], 64 * TOPOLOGY_DONORS)
    return bvh


def _forget(store: Store, mesh_id: str, method: str, leaf_size: int) -> None:
    """Drop a mesh's BVH and the top levels over it: its BVH now holds another mesh."""
    store.discard(bvh_key(mesh_id, method, leaf_size))
    for scene in store.values_of(wire.InstanceScene):
        if any(m.scene_id == mesh_id for m in scene.meshes):
            store.discard(bvh_key(scene.scene_id, method, leaf_size))
            store.discard(culled_key(scene.scene_id, method, leaf_size))
            for role in ROLES:
                store.discard(role_key(scene.scene_id, role, method, leaf_size))


def scene_bvh(store: Store, scene: wire.SceneArrays | wire.InstanceScene, method: str,
              leaf_size: int, device: str, view: View | None = None,
              ) -> tuple[Any, BuildReport]:
    """What a render traces for `scene`, with the report of what it took to have it: a
    single mesh's BVH, or an instance list's two levels (the top level over the meshes'
    BVHs, each from `mesh_bvh`); with a `view`, only what may change its pixels (module
    doc). An instance list is kept in the store with its top level, which lives no longer
    than it (work/store.py drops a scene's BVHs with it). Ray visibility masks are not
    applied here: `scene_views` applies them."""
    from scenesort.kernels.scene import bvh_nbytes as mesh_bytes

    report = BuildReport()
    if isinstance(scene, wire.SceneArrays):
        bvh = mesh_bvh(store, scene, method, leaf_size, device, report)
        report.bvh_bytes = mesh_bytes(bvh)
        return bvh, report
    keep, placed = _cull(store, scene, view, report)
    report.skipped = _unused(scene, keep)
    key = (bvh_key if keep is None else culled_key)(scene.scene_id, method, leaf_size)
    levels = _levels(store, scene, method, leaf_size, device, keep, placed, key, report)
    report.bvh_bytes = levels.nbytes
    return levels, report


@dataclass(frozen=True)
class Views:
    """What a camera render traces (kernels.render_ao's arguments): what the camera sees,
    what occlusion rays meet (often the same object) and what is held out (None: nothing)."""

    camera: Any
    occluders: Any
    holdout: Any | None = None


# An instance list with ray visibility masks: the instances each view holds.
ROLES = {
    "camera": lambda m: ((m & wire.CAMERA) != 0) & ((m & wire.HOLDOUT) == 0),
    "occluders": lambda m: (m & wire.SHADOW) != 0,
    "holdout": lambda m: ((m & wire.CAMERA) != 0) & ((m & wire.HOLDOUT) != 0),
}


def role_key(scene_id: str, role: str, method: str, leaf_size: int) -> str:
    """The cache key of an instance list's top level over one role's instances (kept with
    the mask of which they are, as `culled_key`'s)."""
    return f"{scene_id}/{role}/bvh/{method}/{leaf_size}"


def scene_views(store: Store, scene: wire.SceneArrays | wire.InstanceScene, method: str,
                leaf_size: int, device: str, view: View | None = None,
                ) -> tuple[Views, BuildReport]:
    """`scene_bvh` with the instance list's ray visibility masks applied: a top level per
    role over the instances that have it (and may change a pixel of `view`), on the same
    cached mesh BVHs; one object for the camera and the occluders where their instances
    are the same. Without masks, `scene_bvh`'s levels in both roles."""
    if isinstance(scene, wire.SceneArrays) or scene.visibility is None:
        levels, report = scene_bvh(store, scene, method, leaf_size, device, view)
        return Views(levels, levels), report
    from scenesort.kernels.scene import bvh_nbytes as mesh_bytes

    report = BuildReport()
    keep, placed = _cull(store, scene, view, report)
    if placed is None:  # a role's top level leaves meshes unbuilt: it needs their boxes
        placed = placement(store, scene)[0]
    masks = {role: rule(scene.visibility) & (True if keep is None else keep)
             for role, rule in ROLES.items()}
    report.skipped = _unused(scene, masks["camera"] | masks["occluders"] | masks["holdout"])
    made: dict[str, Any] = {}
    for role, mask in masks.items():
        if role == "holdout" and not mask.any():
            continue  # no holdout in view: nothing to trace for it
        twin = next((r for r in made if np.array_equal(masks[r], mask)), None)
        made[role] = made[twin] if twin is not None else _levels(
            store, scene, method, leaf_size, device, mask, placed,
            role_key(scene.scene_id, role, method, leaf_size), report)
    for name in ("built", "refit", "reused"):  # a mesh of several roles, once
        setattr(report, name, list(dict.fromkeys(getattr(report, name))))
    report.reused = [m for m in report.reused if m not in report.built + report.refit]
    distinct = list({id(levels): levels for levels in made.values()}.values())
    meshes = {id(b): b for levels in distinct for b in levels.meshes if b is not None}
    report.bvh_bytes = sum(mesh_bytes(b) for b in meshes.values()) + sum(
        levels.nbytes - sum(mesh_bytes(b) for b in levels.meshes if b is not None)
        for levels in distinct)
    return Views(made["camera"], made["occluders"], made.get("holdout")), report


def _cull(store: Store, scene: wire.InstanceScene, view: View | None,
          report: BuildReport) -> tuple[np.ndarray | None, Any]:
    """The instances that may change a pixel of `view` (None: all of them) and their
    placement (None without a view)."""
    if view is None:
        return None, None
    keep, placed = report.measure("cull", lambda: visible(store, scene, view))
    report.culled = int(np.count_nonzero(~keep))
    # nothing culled: the scene's own top level, shared with renders without a view
    return (None if not report.culled else keep), placed


def _needed(scene: wire.InstanceScene, keep: np.ndarray | None) -> set[int]:
    """The meshes (indices) of the instances `keep` holds (None: all)."""
    if keep is None:
        return set(range(len(scene.meshes)))
    return set(np.unique(scene.mesh_index[keep]).tolist())


def _unused(scene: wire.InstanceScene, keep: np.ndarray | None) -> list[str]:
    """The ids of the meshes no instance `keep` holds uses: no BVH made or used."""
    needed = _needed(scene, keep)
    return [m.scene_id for k, m in enumerate(scene.meshes) if k not in needed]


def _levels(store: Store, scene: wire.InstanceScene, method: str, leaf_size: int,
            device: str, keep: np.ndarray | None, placed: Any, key: str,
            report: BuildReport) -> Any:
    """The two levels over the instances `keep` holds (None: all), from the store under
    `key` (with the mask they are over, unless all), else built on the meshes' BVHs."""
    from scenesort.kernels.scene import bvh_nbytes as mesh_bytes

    from scenesort import kernels

    needed = _needed(scene, keep)
    levels = store.get(key)
    if keep is not None and levels is not None:
        levels = levels[1] if np.array_equal(levels[0], keep) else None
    if levels is not None:
        report.reused.extend(m.scene_id for k, m in enumerate(scene.meshes) if k in needed)
        if report.top_level != "built":
            report.top_level = "reused"
        return levels
    if scene.scene_id not in store:
        store.put(scene.scene_id, scene, scene.nbytes)
    in_use = frozenset(m.scene_id for m in scene.meshes)
    bottoms = [mesh_bvh(store, m, method, leaf_size, device, report, in_use)
               if k in needed else None for k, m in enumerate(scene.meshes)]
    levels = report.measure("top_level", lambda: kernels.build_scene(
        bottoms, scene.mesh_index, scene.transforms, visible=keep, placed=placed,
        device=device))
    report.top_level = "built"
    # Its own bytes: the meshes' BVHs are entries of their own.
    own = max(levels.nbytes - sum(mesh_bytes(b) for b in bottoms if b is not None), 1)
    store.put(key, levels if keep is None else (keep, levels), own)
    return levels


def get_or_build_bvh(
    store: Any, scene: Any, method: str, leaf_size: int, device: str
) -> tuple[Any, bool]:
    """What a scene traces with these parameters (a mesh's BVH, or an instance list's two
    levels) from the store, else made and stored; (bvh, cached)."""
    bvh, report = scene_bvh(store, scene, method, leaf_size, device)
    return bvh, report.cached


def bvh_for_ao(
    store: Any, scene: Any, method: str | None, leaf_size: int | None, device: str
) -> Any:
    """The BVH an AO request uses: the one asked for (built if missing); with neither
    parameter, the scene's most recently used BVH, else a new sah/8 one."""
    if method is None and leaf_size is None:
        latest = store.latest_with_prefix(f"{scene.scene_id}/bvh/")
        if latest is not None:
            store.get(latest[0])  # a use: refresh its age
            return latest[1]
    bvh, _ = get_or_build_bvh(store, scene, method or "sah", leaf_size or 8, device)
    return bvh
