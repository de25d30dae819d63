"""Frames that redo only what changed: the per-mesh BVH cache, the skip rules, and the
frame renderer that the service's jobs and `scenesort render-frames` both run.

The cache is a `Store` (backend/store.py) keyed by content hash:

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

Culling (a camera render, `View`): before any BVH, the instances that may change a pixel
are decided from the meshes' object boxes (`cull.mesh_box`, kept per mesh under
`box_key`) under the transforms (the placement, kept per list under `placement_key`) and
the AO distance (the request's, else the scene default over all instances, culled ones
too, as `render_ao` computes it from the culled scene's bounds): only the meshes of those
instances are built or refit (a mesh out of view waits until it enters it), and the top
level is over those instances, kept under `culled_key` with which they are. A camera-only
change that leaves the same instances in view builds nothing; one that changes them
builds the top level (and the meshes coming into view). Nothing culled: the scene's own
top level (`bvh_key`), as without a camera.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from scenesort.backend.render.bundle import Bundle, read_bundle
from scenesort.backend.wire import binary as wire
from scenesort.backend.work.store import Store, bvh_key, bvh_nbytes

TopLevel = Literal["built", "reused", "none"]
DEFAULT_CACHE_BYTES = 4096 * 2**20


def topology_key(topology: str, method: str, leaf_size: int) -> str:
    """The cache key naming the last mesh with this topology whose BVH was made."""
    return f"{topology}/topology/{method}/{leaf_size}"


def culled_key(scene_id: str, method: str, leaf_size: int) -> str:
    """The cache key of an instance list's top level over the instances a camera sees
    (kept with the mask of which they are; not a `bvh_key`: AO on explicit rays, which
    takes a scene's latest BVH, must not find it)."""
    return f"{scene_id}/culled/bvh/{method}/{leaf_size}"


def placement_key(scene_id: str) -> str:
    """The cache key of an instance list's placement (`place_instances`) and its meshes'
    largest triangle sides: what culling needs of it, whatever the camera."""
    return f"{scene_id}/placed"


def box_key(mesh_id: str) -> str:
    """The cache key of a mesh's object box and largest triangle side (`cull.mesh_box`)."""
    return f"{mesh_id}/box"


@dataclass(frozen=True)
class View:
    """What a camera render sees: the framed camera and the AO distance (None: the scene
    default)."""

    camera: Any
    distance: float | None


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


def scene_bvh(store: Store, scene: wire.SceneArrays | wire.InstanceScene, method: str,
              leaf_size: int, device: str, view: View | None = None,
              ) -> tuple[Any, BuildReport]:
    """What a render traces for `scene`, with the report of what it took to have it: a
    single mesh's BVH, or an instance list's two levels (the top level over the meshes'
    BVHs, each from `mesh_bvh`); with a `view`, only what may change its pixels (module
    doc). An instance list is kept in the store with its top level, which lives no longer
    than it (store.py drops a scene's BVHs with it)."""
    from scenesort.kernels.scene import bvh_nbytes as mesh_bytes

    from scenesort import kernels

    report = BuildReport()
    if isinstance(scene, wire.SceneArrays):
        bvh = mesh_bvh(store, scene, method, leaf_size, device, report)
        report.bvh_bytes = mesh_bytes(bvh)
        return bvh, report
    keep, placed = None, None
    if view is not None:
        keep, placed = report.measure("cull", lambda: visible(store, scene, view))
        report.culled = int(np.count_nonzero(~keep))
        if not report.culled:
            keep = None  # the scene's own top level, shared with renders without a view
    needed = (set(range(len(scene.meshes))) if keep is None
              else set(np.unique(scene.mesh_index[keep]).tolist()))
    report.skipped = [m.scene_id for k, m in enumerate(scene.meshes) if k not in needed]
    key = (bvh_key if keep is None else culled_key)(scene.scene_id, method, leaf_size)
    levels = store.get(key)
    if keep is not None and levels is not None:
        levels = levels[1] if np.array_equal(levels[0], keep) else None
    if levels is not None:
        report.reused.extend(m.scene_id for k, m in enumerate(scene.meshes) if k in needed)
        report.top_level = "reused"
        report.bvh_bytes = levels.nbytes
        return levels, report
    if scene.scene_id not in store:
        store.put(scene.scene_id, scene, scene.nbytes)
    in_use = frozenset(m.scene_id for m in scene.meshes)
    bottoms = [mesh_bvh(store, m, method, leaf_size, device, report, in_use)
               if k in needed else None for k, m in enumerate(scene.meshes)]
    levels = report.measure("top_level", lambda: kernels.build_scene(
        bottoms, scene.mesh_index, scene.transforms, visible=keep, placed=placed,
        device=device))
    report.top_level = "built"
    report.bvh_bytes = levels.nbytes
    # Its own bytes: the meshes' BVHs are entries of their own.
    own = max(levels.nbytes - sum(mesh_bytes(b) for b in bottoms if b is not None), 1)
    store.put(key, levels if keep is None else (keep, levels), own)
    return levels, report


def visible(store: Store, scene: wire.InstanceScene, view: View) -> tuple[np.ndarray, Any]:
    """The instances that may change a pixel of the view's AO image (`cull.
    visible_instances`), decided from the meshes' boxes before any BVH is made, and their
    placement (`place_instances`, which `build_scene` then reuses). The placement and the
    meshes' triangle sizes depend on the instance list alone: kept under `placement_key`,
    so a camera-only change pays the planes' test only."""
    from scenesort.kernels.render import default_distance
    from scenesort.kernels.render.cull import mesh_box, visible_instances
    from scenesort.kernels.scene.api import place_instances

    kept = store.get(placement_key(scene.scene_id))
    if kept is None:
        found = []
        for mesh in scene.meshes:
            box = store.get(box_key(mesh.scene_id))
            if box is None:
                box = mesh_box(mesh.vertices, mesh.indices)
                store.put(box_key(mesh.scene_id), box, 64)
            found.append(box)
        placed = place_instances(np.stack([b for b, _ in found]), scene.mesh_index,
                                 scene.transforms)
        kept = placed, np.array([e for _, e in found])
        held = [placed.lo, placed.hi, placed.mesh_ids, placed.transforms, *placed.frames.values()]
        store.put(placement_key(scene.scene_id), kept, sum(a.nbytes for a in held))
    placed, extents = kept
    # The scene default over every instance: render_ao's from the culled scene's bounds,
    # which are the placement's (build_scene counts the culled instances' boxes).
    distance = default_distance(placed) if view.distance is None else view.distance
    return visible_instances(placed, extents, view.camera, distance), placed


def resolve(listing: wire.InstanceList,
            mesh: Callable[[str], wire.SceneArrays | None]) -> wire.InstanceScene:
    """The instance list with its meshes looked up by id (`mesh` returns None for one it
    lacks: KeyError naming the first such id). ValueError for a mesh whose terminator
    offsets vary over its triangles: an instance has one (Blender's is per object)."""
    meshes = []
    for k, mesh_id in enumerate(listing.mesh_ids):
        found = mesh(mesh_id)
        if found is None:
            raise KeyError(mesh_id)
        offsets = found.terminator_offsets
        if offsets is not None and np.any(offsets != offsets[0]):
            raise ValueError(f"mesh {k} ({mesh_id}) has terminator offsets that vary over "
                             "its triangles; in an instance list each mesh has one (send it "
                             "repeated, as the object's value)")
        meshes.append(found)
    return wire.InstanceScene(listing.scene_id, tuple(meshes), listing.mesh_index,
                              listing.transforms)


# --- the frame renderer ---------------------------------------------------------------


@dataclass
class FrameResult:
    """One rendered frame: AO, coverage and depth (height, width) float32, row 0 at the
    top, as the service's job result has them; its PNG; what the build did; timings."""

    frame: int
    ao: np.ndarray
    coverage: np.ndarray
    depth: np.ndarray
    png: bytes
    build: BuildReport
    timings_ms: dict[str, float]


class FrameRenderer:
    """Renders a bundle's frames in any order, keeping the BVHs between them (`cache_bytes`
    bounds what it keeps). Each frame is the service's camera job on the frame's instance
    list, so the images are the service's; `cull` False builds what is out of view too
    (the same images: the tests' and benchmarks' reference)."""

    def __init__(self, bundle: Bundle | str | Path, *, device: str | None = None,
                 threads: int | None = None, cache_bytes: int = DEFAULT_CACHE_BYTES,
                 cull: bool = True) -> None:
        # Anything with the Bundle's frame() and mesh(): backend/cluster.py ships frames in
        # tasks and meshes through Ray's object store.
        self.bundle = read_bundle(bundle) if isinstance(bundle, str | Path) else bundle
        self.device = device or "cpu"
        self.threads = threads
        self.store = Store(cache_bytes)
        self.cull = cull  # False: every mesh built, the top level over every instance

    def _mesh(self, mesh_id: str) -> wire.SceneArrays:
        found = self.store.get(mesh_id)
        if found is None:
            found = self.bundle.mesh(mesh_id)
            self.store.put(mesh_id, found, found.nbytes)
        return found

    def render(self, frame_number: int) -> FrameResult:
        """Render one frame (its meshes read from the bundle when first needed)."""
        from scenesort.backend.work import jobs  # which imports this module for scene_bvh

        frame = self.bundle.frame(frame_number)
        request = frame.request
        scene = resolve(frame.instances, self._mesh)
        camera = jobs.job_camera(request)
        job = jobs.Job(job_id=f"frame-{frame_number}", scene_id=scene.scene_id,
                       width=camera.width, height=camera.height)
        params = jobs.ao_params(request, threads=self.threads)
        jobs.render_camera(job, self.store, scene, camera, params, request.method,
                           request.leaf_size, self.device, cull=self.cull)
        assert job.ao is not None and job.coverage is not None and job.depth is not None
        return FrameResult(frame_number, job.ao, job.coverage, job.depth, job.png or b"",
                           job.build or BuildReport(), dict(job.timings_ms))


def frame_paths(out_dir: Path, frame_number: int) -> tuple[Path, Path]:
    """Where a frame's 8-bit PNG and float32 AO (.npy) go."""
    stem = Path(out_dir) / f"{frame_number:06d}"
    return stem.with_suffix(".png"), stem.with_suffix(".npy")


def frame_done(out_dir: Path, frame_number: int) -> bool:
    """Whether the frame's files are in `out_dir` (what `resume` skips)."""
    return all(path.exists() for path in frame_paths(out_dir, frame_number))


def write_frame(out_dir: str | Path, frame_number: int, result: FrameResult) -> Path:
    """Write the frame's PNG (the service's `format=png`) and its float32 AO as .npy
    (row 0 at the top); returns the PNG's path."""
    png, npy = frame_paths(Path(out_dir), frame_number)
    png.parent.mkdir(parents=True, exist_ok=True)
    np.save(npy, result.ao.astype(np.float32))
    png.write_bytes(result.png)  # last: a frame counts as done (resume) once its PNG exists
    return png


@contextmanager
def frame_progress(total: int, enabled: bool = True) -> Iterator[Callable[[int], None]]:
    """A rich progress bar over `total` frames; yields `advance(frame)`, called as each frame
    is done (a no-op when not `enabled`)."""
    if not enabled:
        yield lambda number: None
        return
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
               TimeElapsedColumn(), TimeRemainingColumn())
    with Progress(*columns, transient=True) as bar:
        task = bar.add_task("frames", total=total)
        yield lambda number: bar.update(task, advance=1, description=f"frame {number}")


def render_frames(bundle_path: str | Path, out_dir: str | Path, *,
                  frames: Iterable[int] | None = None, resume: bool = False,
                  threads: int | None = None, progress: bool = True,
                  device: str | None = None) -> list[tuple[int, BuildReport | None]]:
    """Render the bundle's frames (all, or `frames`) into `out_dir`, with a rich progress
    bar; `resume` skips frames whose files exist. Returns (frame, report) per frame, the
    report None for a frame skipped."""
    renderer = FrameRenderer(bundle_path, device=device, threads=threads)
    wanted = list(renderer.bundle.frames if frames is None else frames)
    done: list[tuple[int, BuildReport | None]] = []
    with frame_progress(len(wanted), progress) as advance:
        for number in wanted:
            if resume and frame_done(Path(out_dir), number):
                done.append((number, None))
            else:
                result = renderer.render(number)
                write_frame(out_dir, number, result)
                done.append((number, result.build))
            advance(number)
    return done
