"""Scenes that change: refit against rebuild, and instances against the flattened scene,
with the dynamic-scene floors (docs/benchmarks.md, "Dynamic scenes").

    python benchmarks/animation.py [--part refit|instances|frames|cull|all] [--repeat 3]
        [--no-docs] [--subdivide 2] [--instances 1000] [--flat-instances 256] [--size 384]
        [--frames 100] [--frame-instances 200] [--frame-triangles 6000] [--frame-size 64]
        [--flat-every 5] [--cull-frames 40] [--cull-side 30] [--cull-triangles 50000]

refit: the bunny subdivided `--subdivide` times (4x triangles each: 2 -> 1.1 M) and deformed
  by a smooth wave, frame after frame: `refit_bvh` of the deformed mesh against `build_bvh`
  of it (same options, every core), medians of interleaved runs after a warm-up. Then the
  rebuild rule's measurement: for growing deformations, the refit tree's SAH ratio and its
  trace time (camera rays, closest hit) against a fresh build's.
instances: `--instances` bunnies (rotated, scaled, on a grid): the scene's device bytes
  against one bunny's plus the top level's; trace speed (camera rays closest hit, and AO)
  of the two-level scene against the flattened one at `--flat-instances` (256 by default:
  flattening 1,000 bunnies, 69 M triangles, does not fit this machine's memory beside
  other work).
frames: `--frames` frames of one deforming bunny (full resolution) among
  `--frame-instances` instances of the bunny, dragon and buddha (vertex-clustered to about
  `--frame-triangles` triangles each) and an orbiting camera, through a real `scenesort
  serve`: per frame the flattened scene hashed, uploaded and built (POST /v1/scenes, a job),
  against the meshes and instance list with only what changed sent (HEAD first) and built
  (a refit and a top level); interleaved frame by frame after two warm-up frames, the
  flattened path (the same work every frame) on every `--flat-every`-th frame.
cull: a field larger than the view (`--cull-side` squared instances of 12 meshes: bunny, dragon
  and buddha vertex-clustered to `--cull-triangles`, four waves each; a mesh per region
  of the grid) and a low camera
  moving across it for `--cull-frames` frames, rendered in this process by two
  `FrameRenderer`s, culling on and off, interleaved frame by frame: time per frame, BVH
  bytes traced, meshes built, images compared. Then the camera-only frame's cost with
  `--instances` bunnies: the cull decision (`frames.visible`, the placement cached) and
  the top level over the instances in view, against the top level over all of them.
Warp's compile time is paid in the warm-up and not counted. Writes its sections of
docs/benchmarks.md ("Dynamic scenes"), marked as measured on a loaded machine.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import httpx
import numpy as np
import trimesh
import warp as wp

wp.config.quiet = True

from docs_section import write_section  # noqa: E402  (benchmarks/ is on sys.path)
from scenesort.backend.render.scenes import load_mesh, shared_scene, shared_scenes_dir  # noqa: E402
from scenesort.backend.wire import binary as wire  # noqa: E402
from scenesort.kernels import Camera  # noqa: E402
from scenesort.kernels.core import cpu_cores  # noqa: E402
from scenesort.kernels.render import default_distance  # noqa: E402
from scenesort.kernels.scene import bvh_nbytes  # noqa: E402

from scenesort import kernels  # noqa: E402

REFIT_FLOOR = 0.3  # refit time / rebuild time, at most
MEMORY_FLOOR = 1.1  # scene bytes / (one bunny + top level), at most
TRACE_FLOOR = 0.7  # two-level trace speed / flattened, at least
FRAMES_FLOOR = 0.25  # two-level frames' total time / the flattened scene's, at most
STATIC = ("bunny", "dragon", "buddha")  # frames: the instanced meshes
DEFORMER = "bunny"  # frames: the deforming mesh, at full resolution
OCTET = {"Content-Type": "application/octet-stream"}
WAVES = (0.0, 0.02, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4)  # deformation amplitudes, of the box diagonal


def median_ms(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(times))


def cpu_ms(fn) -> float:
    """The process's CPU time of fn() (every host thread's): on a machine shared with other
    work the steadiest measure of work done (another process's load does not count)."""
    t0 = time.process_time()
    fn()
    return (time.process_time() - t0) * 1e3


def time_ratio(run, a, b, repeat: int) -> float:
    """Median over `repeat` interleaved pairs of run(a)'s CPU time over run(b)'s, after a
    warm-up of each."""
    run(a)
    run(b)
    return float(np.median([cpu_ms(lambda: run(a)) / cpu_ms(lambda: run(b))
                            for _ in range(repeat)]))


def load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def deform(v: np.ndarray, amount: float, phase: float) -> np.ndarray:
    """A smooth wave through the mesh: each coordinate pushed by a sine of another,
    `amount` times the box diagonal."""
    lo, hi = v.min(axis=0), v.max(axis=0)
    diag = float(np.linalg.norm(hi - lo))
    x = (v - lo) / (hi - lo) * 2.0 * np.pi
    push = np.sin(2.0 * x[:, [1, 2, 0]] + phase)
    return (v + amount * diag * push).astype(np.float32)


def camera_rays(camera, size: int):
    c = type(camera).from_dict({**camera.to_dict(), "width": size, "height": size * 3 // 4})
    return c.rays()


def part_refit(args) -> tuple[list[str], dict]:
    scene = shared_scene("bunny")
    v, f = scene.vertices.astype(np.float64), scene.indices
    for _ in range(args.subdivide):
        v, f = trimesh.remesh.subdivide(v, f)
    v, f = v.astype(np.float32), f.astype(np.int32)
    print(f"refit: bunny subdivided {args.subdivide}x: {len(f):,} triangles")
    o, d, tmin, tmax = camera_rays(scene.camera, args.size)
    bvh = kernels.build_bvh(v, f)
    kernels.refit_bvh(bvh, deform(v, 0.01, 0.0), rebuild_ratio=np.inf)  # warm-up: compile
    refit, rebuild = [], []
    for k in range(args.repeat):  # frames of the animation, the two interleaved
        frame = deform(v, 0.01, 0.3 * (k + 1))
        t0 = time.perf_counter()
        out = kernels.refit_bvh(bvh, frame, rebuild_ratio=np.inf)
        refit.append((time.perf_counter() - t0) * 1e3)
        t0 = time.perf_counter()
        kernels.build_bvh(frame, f)
        rebuild.append((time.perf_counter() - t0) * 1e3)
    refit_ms, rebuild_ms = float(np.median(refit)), float(np.median(rebuild))
    phases = out.stats.phase_ms
    rows = []
    for amount in WAVES:
        frame = deform(v, amount, 1.0)
        refit_tree = kernels.build_bvh(v, f)
        refit_tree = kernels.refit_bvh(refit_tree, frame, rebuild_ratio=np.inf)
        fresh = kernels.build_bvh(frame, f)
        dist = default_distance(fresh)

        def trace_rays(t):
            kernels.trace(t, o, d, tmin, tmax)

        def render(t, dist=dist):
            kernels.render_ao(t, o, d, spp=4, distance=dist, tmin=tmin, tmax=tmax)

        row = {"amount": amount, "sah_ratio": refit_tree.stats.sah_ratio,
               "fresh_ratio": fresh.stats.sah_cost / refit_tree.stats.build_sah_cost,
               "trace": time_ratio(trace_rays, refit_tree, fresh, args.repeat),
               "ao": time_ratio(render, refit_tree, fresh, args.repeat)}
        rows.append(row)
        print(f"  wave {amount:5.2f}: SAH refit/built {row['sah_ratio']:.3f}, fresh/built "
              f"{row['fresh_ratio']:.3f}, refit/fresh trace {row['trace']:.3f} AO {row['ao']:.3f}")
    ratio = refit_ms / rebuild_ms
    lines = [
        f"Run: `{args.command}`, load average {load()} on {cpu_cores()} cores (shared with "
        "other work: indicative figures; the ratios are of the same run).",
        "",
        f"Refit of the bunny subdivided {args.subdivide}x ({len(f):,} triangles, width "
        f"{bvh.stats.width}) under a smooth wave (1% of the diagonal), frame after frame, "
        f"medians of {args.repeat} interleaved runs:",
        "",
        "| | ms |",
        "|---|---:|",
        f"| rebuild (`build_bvh`) | {rebuild_ms:.0f} |",
        f"| refit (`refit_bvh`) | {refit_ms:.0f} |",
        *(f"| refit phase {k} | {x:.1f} |" for k, x in phases.items()),
        f"| **refit / rebuild** | **{ratio:.3f}** (floor <= {REFIT_FLOOR}: "
        f"{'met' if ratio <= REFIT_FLOOR else 'NOT met'}) |",
        "",
        f"The rebuild rule's measurement (`REBUILD_RATIO` = {kernels.REBUILD_RATIO}): waves of "
        f"growing amplitude; CPU time (both host threads; steadier than wall time under "
        f"load) of closest-hit camera rays ({len(o):,}) and of a 4-spp AO render of them "
        "through the refit tree over a fresh build's of the deformed mesh (medians of "
        f"{args.repeat} interleaved ratios).",
        "",
        "| wave (x diagonal) | SAH refit / built | SAH fresh / built | trace refit / fresh | "
        "AO refit / fresh |",
        "|---:|---:|---:|---:|---:|",
        *(f"| {r['amount']:.2f} | {r['sah_ratio']:.3f} | {r['fresh_ratio']:.3f} | "
          f"{r['trace']:.3f} | {r['ao']:.3f} |" for r in rows),
    ]
    return lines, {"refit_ratio": ratio}


def bunny_field(count: int, v: np.ndarray, seed: int = 0) -> np.ndarray:
    """`count` transforms: bunnies on a square grid 0.7 bunny diagonals apart, each rotated
    about the vertical and scaled by 0.8-1.2 (one in ten mirrored)."""
    rng = np.random.default_rng(seed)
    size = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    side = int(np.ceil(np.sqrt(count)))
    out = np.zeros((count, 3, 4), np.float32)
    for k in range(count):
        a = rng.uniform(0, 2 * np.pi)
        rot = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        s = rng.uniform(0.8, 1.2) * np.array([-1.0 if k % 10 == 9 else 1.0, 1.0, 1.0])
        out[k, :, :3] = rot * s
        out[k, :, 3] = (0.7 * size * (k % side), 0.0, 0.7 * size * (k // side)) - v.mean(axis=0)
    return out


def field_camera(scene: kernels.Scene, size: int) -> tuple[np.ndarray, ...]:
    lo, hi = scene.bounds
    mid = 0.5 * (lo + hi)
    span = float(np.linalg.norm(hi - lo))
    cam = kernels.Camera.look_at(mid + np.array([0.0, 0.15, -0.5]) * span, mid, (0, 1, 0), 50,
                                 size, size * 3 // 4, clip_start=0.0, clip_end=1e10)
    return cam.rays()


def trace_pair(label: str, scene: kernels.Scene, flat: kernels.Bvh | None, args) -> dict:
    """Median ms of closest-hit camera rays and of a 4-spp AO render, two-level against
    flattened (interleaved)."""
    o, d, tmin, tmax = field_camera(scene, args.size)
    dist = default_distance(scene)
    tracers = {"scene": scene} | ({"flat": flat} if flat is not None else {})
    for t in tracers.values():  # warm-up
        kernels.trace(t, o, d, tmin, tmax)
        kernels.render_ao(t, o, d, spp=1, distance=dist, tmin=tmin, tmax=tmax)
    out: dict[str, list[float]] = {f"{k} {w}": [] for k in tracers for w in ("trace", "ao")}
    for _ in range(args.repeat):
        for k, t in tracers.items():
            out[f"{k} trace"].append(median_ms(lambda t=t: kernels.trace(t, o, d, tmin, tmax), 1))
            out[f"{k} ao"].append(median_ms(
                lambda t=t: kernels.render_ao(t, o, d, spp=4, distance=dist, tmin=tmin,
                                              tmax=tmax), 1))
    res = {k: float(np.median(x)) for k, x in out.items()}
    res["rays"] = len(o)
    res["hit"] = float(kernels.trace(scene, o, d, tmin, tmax).hit.mean())
    print(f"  {label}: " + ", ".join(f"{k} {x:.0f} ms" for k, x in res.items()
                                     if k not in ("rays", "hit")))
    return res


def part_instances(args) -> tuple[list[str], dict]:
    bunny = shared_scene("bunny")
    v, f = bunny.vertices, bunny.indices
    bvh = kernels.build_bvh(v, f)
    one = bvh_nbytes(bvh)
    ts = bunny_field(args.instances, v)
    ids = np.zeros(args.instances, np.int32)
    kernels.build_scene([bvh], ids, ts)  # warm-up
    build_ms = median_ms(lambda: kernels.build_scene([bvh], ids, ts), args.repeat)
    scene = kernels.build_scene([bvh], ids, ts)
    top = scene.nbytes - one
    print(f"instances: {args.instances} bunnies: scene {scene.nbytes / 2**20:.1f} MiB, one bunny "
          f"{one / 2**20:.1f} MiB, top level and records {top / 2**10:.0f} KiB, top level "
          f"built in {build_ms:.1f} ms")
    small_ts = bunny_field(args.flat_instances, v)
    small = kernels.build_scene([bvh], ids[: args.flat_instances], small_ts)
    world = (np.einsum("nij,kj->nki", small_ts[:, :, :3].astype(np.float64), v.astype(np.float64))
             + small_ts[:, None, :, 3]).astype(np.float32).reshape(-1, 3)
    faces = (f[None] + (np.arange(args.flat_instances) * len(v))[:, None, None]).reshape(-1, 3)
    t0 = time.perf_counter()
    flat = kernels.build_bvh(world, faces.astype(np.int32))
    flat_build_ms = (time.perf_counter() - t0) * 1e3
    flat_bytes_per_bunny = bvh_nbytes(flat) / args.flat_instances
    at_small = trace_pair(f"{args.flat_instances} instances", small, flat, args)
    del flat
    at_full = trace_pair(f"{args.instances} instances", scene, None, args)
    mem_ratio = scene.nbytes / (one + top)
    speed = {w: at_small[f"flat {w}"] / at_small[f"scene {w}"] for w in ("trace", "ao")}
    n_flat = args.flat_instances
    lines = [
        f"Run: `{args.command}`, load average {load()} on {cpu_cores()} cores (shared with "
        "other work: indicative figures; the ratios are of the same run).",
        "",
        f"Memory of {args.instances:,} instances of the bunny ({len(f):,} triangles; device "
        "bytes: BVH, mesh, instance records, top level):",
        "",
        "| | MiB |",
        "|---|---:|",
        f"| one bunny (BVH width {bvh.stats.width} and mesh) | {one / 2**20:.2f} |",
        f"| top level and instance records | {top / 2**20:.3f} |",
        f"| two-level scene | {scene.nbytes / 2**20:.2f} |",
        f"| flattened, extrapolated ({n_flat} bunnies measured) | "
        f"{args.instances * flat_bytes_per_bunny / 2**20:,.0f} |",
        f"| **scene / (one bunny + top level)** | **{mem_ratio:.3f}** (floor <= {MEMORY_FLOOR}: "
        f"{'met' if mem_ratio <= MEMORY_FLOOR else 'NOT met'}) |",
        "",
        f"Top level of {args.instances:,} instances built in {build_ms:.1f} ms (median of "
        f"{args.repeat}); the flattened {n_flat} bunnies ({n_flat * len(f):,} triangles) in "
        f"{flat_build_ms:.0f} ms.",
        "",
        f"Trace speed, {at_small['rays']:,} camera rays ({at_small['hit']:.0%} hit), medians "
        f"of {args.repeat} interleaved runs: the two-level scene against the flattened one "
        f"at {n_flat} instances (flattening {args.instances:,} bunnies, "
        f"{args.instances * len(f) / 1e6:.0f} M triangles, needs about "
        f"{args.instances * flat_bytes_per_bunny / 2**30:.0f} GiB for its BVH and mesh alone "
        "and about twice that while it is built: more than this 23 GB machine spares beside "
        "the other work), and the two-level scene alone at the full count.",
        "",
        "| instances | closest hit ms (two-level / flat) | AO 4 spp ms (two-level / flat) | "
        "speed two-level / flat |",
        "|---:|---:|---:|---:|",
        f"| {n_flat} | {at_small['scene trace']:.0f} / {at_small['flat trace']:.0f} | "
        f"{at_small['scene ao']:.0f} / {at_small['flat ao']:.0f} | trace {speed['trace']:.2f}, "
        f"AO {speed['ao']:.2f} (floor >= {TRACE_FLOOR}: "
        f"{'met' if min(speed.values()) >= TRACE_FLOOR else 'NOT met'}) |",
        f"| {args.instances:,} | {at_full['scene trace']:.0f} / - | {at_full['scene ao']:.0f} / - "
        "| - |",
    ]
    return lines, {"memory_ratio": mem_ratio, **{f"speed_{k}": x for k, x in speed.items()}}


def decimate(vertices: np.ndarray, indices: np.ndarray, target: int) -> tuple[np.ndarray,
                                                                             np.ndarray]:
    """Vertex clustering on a grid, made finer until at least `target` triangles remain:
    a low-poly copy of a shared mesh (collapsed and repeated triangles dropped)."""
    lo, extent = vertices.min(0), float(np.ptp(vertices, axis=0).max())
    for cells in (8, 12, 16, 24, 32, 48, 64, 96, 128, 192, 256, 384, 512):
        key = np.minimum(((vertices - lo) / extent * cells).astype(np.int64), cells)
        flat = (key[:, 0] * (cells + 1) + key[:, 1]) * (cells + 1) + key[:, 2]
        _, inverse, counts = np.unique(flat, return_inverse=True, return_counts=True)
        merged = np.zeros((len(counts), 3))
        np.add.at(merged, inverse, vertices)
        tris = inverse[indices]
        keep = ((tris[:, 0] != tris[:, 1]) & (tris[:, 1] != tris[:, 2])
                & (tris[:, 0] != tris[:, 2]))
        _, first = np.unique(np.sort(tris[keep], axis=1), axis=0, return_index=True)
        tris = tris[keep][np.sort(first)]
        if len(tris) >= target or cells == 512:
            return (merged / counts[:, None]).astype(np.float32), tris.astype(np.int32)
    raise AssertionError("unreachable")


def unit(vertices: np.ndarray) -> np.ndarray:
    """Centred on the origin, its longest side 1."""
    lo, hi = vertices.min(0), vertices.max(0)
    return ((vertices - (lo + hi) / 2) / float((hi - lo).max())).astype(np.float32)


def body_of(vertices: np.ndarray, indices: np.ndarray) -> bytes:
    return vertices.astype("<f4").tobytes() + indices.astype("<i4").tobytes()


class Animation:
    """One deforming bunny among `instances` instances of three low-poly shared meshes on
    a grid, and a camera orbiting them; frame k's arrays, the same for both paths."""

    def __init__(self, instances: int, triangles: int, width: int, height: int) -> None:
        folder = shared_scenes_dir()
        if folder is None:
            raise SystemExit("no shared scenes folder: set $SCENESORT_SCENES")
        self.static = []
        for name in STATIC:
            v, f = load_mesh(folder / f"{name}.ply")
            v, f = decimate(unit(v), f, triangles)
            self.static.append((v, f))
        v, f = load_mesh(folder / f"{DEFORMER}.ply")
        self.rest, self.deformer_indices = unit(v) * 3.0, f
        rng = np.random.default_rng(7)
        side = int(np.ceil(np.sqrt(instances)))
        self.mesh_index = np.arange(instances, dtype=np.int32) % len(STATIC)
        self.transforms = np.zeros((instances, 3, 4), np.float32)
        for i in range(instances):
            angle, scale = rng.uniform(0, 2 * np.pi), rng.uniform(0.6, 1.0)
            c, s = np.cos(angle), np.sin(angle)
            rotation = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]) * scale
            x, z = (i % side - side / 2) * 1.3, (i // side - side / 2) * 1.3
            self.transforms[i, :, :3] = rotation
            self.transforms[i, :, 3] = (x, 0.0, z)
        self.radius = 1.3 * side * 0.75
        self.size = (width, height)

    def deformed(self, frame: int) -> np.ndarray:
        """The bunny under a travelling wave (same topology every frame), above the grid."""
        return deform(self.rest, 0.03, 0.3 * frame) + np.float32([0.0, 1.5, 0.0])

    def camera(self, frame: int) -> dict:
        angle = 2 * np.pi * frame / 100.0
        position = (self.radius * np.cos(angle), 0.6 * self.radius, self.radius * np.sin(angle))
        cam = Camera.look_at(position, (0.0, 0.5, 0.0), (0, 1, 0), 50.0, *self.size,
                             clip_start=0.01, clip_end=1e4)
        return cam.to_dict()

    def flattened(self, deformed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The frame as one world-space triangle list, as a flattening client sends it."""
        vertices, indices, start = [], [], 0
        for k, m in zip(self.mesh_index, self.transforms, strict=True):
            v, f = self.static[k]
            vertices.append(v @ m[:, :3].T + m[:, 3])
            indices.append(f + start)
            start += len(v)
        vertices.append(deformed)
        indices.append(self.deformer_indices + start)
        return np.concatenate(vertices).astype(np.float32), np.concatenate(indices)


class Session:
    """httpx against one service, the job settings fixed."""

    def __init__(self, url: str, auth: dict[str, str], settings: dict) -> None:
        self.http = httpx.Client(base_url=url, headers=auth, timeout=600)
        self.settings = settings

    def render(self, scene_id: str, camera: dict) -> dict:
        job = self.http.post("/v1/jobs", json={"scene_id": scene_id, "camera": camera,
                                               **self.settings})
        job.raise_for_status()
        job_id = job.json()["job_id"]
        while True:
            status = self.http.get(f"/v1/jobs/{job_id}").json()
            if status["state"] not in ("queued", "running"):
                break
            time.sleep(0.002)
        if status["state"] != "done":
            raise SystemExit(f"job failed: {status}")
        self.http.get(f"/v1/jobs/{job_id}/result", params={"format": "f32"}).raise_for_status()
        return status

    def flat_frame(self, anim: Animation, frame: int, deformed: np.ndarray) -> dict:
        v, f = anim.flattened(deformed)
        body = body_of(v, f)
        scene_id = wire.scene_hash(len(v), len(f), body)
        if self.http.head(f"/v1/scenes/{scene_id}").status_code == 404:
            self.http.post("/v1/scenes", params={"vertices": len(v), "triangles": len(f)},
                           content=body, headers=OCTET).raise_for_status()
        return self.render(scene_id, anim.camera(frame))

    def instanced_frame(self, anim: Animation, frame: int, deformed: np.ndarray) -> dict:
        meshes = [*anim.static, (deformed, anim.deformer_indices)]
        ids = []
        for v, f in meshes:
            body = body_of(v, f)
            ids.append(wire.scene_hash(len(v), len(f), body))
            if self.http.head(f"/v1/meshes/{ids[-1]}").status_code == 404:
                self.http.put(f"/v1/meshes/{ids[-1]}", content=body, headers=OCTET,
                              params={"vertices": len(v), "triangles": len(f)}
                              ).raise_for_status()
        index = np.append(anim.mesh_index, len(STATIC)).astype("<i4")
        placed = np.concatenate([anim.transforms, np.eye(3, 4, dtype=np.float32)[None]])
        body = "".join(ids).encode() + index.tobytes() + placed.astype("<f4").tobytes()
        scene_id = wire.instances_hash(len(ids), len(index), body)
        if self.http.head(f"/v1/scenes/{scene_id}").status_code == 404:
            self.http.post("/v1/instance-scenes", content=body, headers=OCTET,
                           params={"meshes": len(ids), "instances": len(index)}
                           ).raise_for_status()
        return self.render(scene_id, anim.camera(frame))


def part_frames(args) -> tuple[list[str], dict]:
    """Both paths frame by frame, interleaved, through one `scenesort serve`: per frame the
    flattened scene uploaded and built, then the meshes and instance list with only what
    changed sent and built. Frame 0 of each is the warm-up (Warp's compile, the first
    builds) and not counted."""
    from service import start_service  # benchmarks/service.py

    width = args.frame_size
    anim = Animation(args.frame_instances, args.frame_triangles, width, width * 3 // 4)
    proc, url, auth = start_service()
    try:
        lines, figures = _frames(args, anim, Session(url, auth, {
            "spp": args.frame_spp, "seed": 1, "distance": 0.5}))
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    return lines, figures


WARM_UP = 2  # frames before the timed ones: the first builds, then the first refit (compile)


def _frames(args, anim: Animation, session: Session) -> tuple[list[str], dict]:
    """Frames -WARM_UP..-1 warm up; of frames 0..frames-1 the two-level path runs every one
    and the flattened path every `--flat-every`-th, interleaved (its total is its mean
    frame times the frames: every flattened frame is the same work, a full upload and
    build)."""
    times: dict[str, list[float]] = {"flattened": [], "two levels": []}
    phases: dict[str, dict[str, float]] = {k: {"bvh": 0.0, "ao": 0.0} for k in times}
    reports = []
    for frame in range(-WARM_UP, args.frames):
        deformed = anim.deformed(frame)
        paths = [("two levels", session.instanced_frame)]
        if frame % args.flat_every == 0 and (frame >= 0 or frame == -WARM_UP):
            paths.insert(0, ("flattened", session.flat_frame))
        for name, run in paths:
            start = time.perf_counter()
            status = run(anim, frame, deformed)
            elapsed = time.perf_counter() - start
            if frame < 0:
                continue
            times[name].append(elapsed)
            for phase in phases[name]:
                phases[name][phase] += status["timings_ms"].get(phase, 0.0) / 1e3
            if name == "two levels":
                reports.append(status["build"])
    scale = {"flattened": args.frames / len(times["flattened"]), "two levels": 1.0}
    total = {name: sum(t) * scale[name] for name, t in times.items()}
    flat_tris = len(anim.flattened(anim.deformed(0))[1])
    refits = sum(len(r["refit"]) for r in reports)
    built = sum(len(r["built"]) for r in reports)
    width, height = anim.size
    lines = [
        f"Run: `{args.command}`, load average {load()} on {cpu_cores()} cores (shared with "
        "other work: indicative figures; the ratio is of the same run).",
        "",
        f"{args.frames} frames, {width}x{height}, spp {args.frame_spp}: one deforming bunny "
        f"({len(anim.deformer_indices):,} triangles) and {len(anim.mesh_index)} instances "
        f"of {', '.join(STATIC)} (vertex-clustered to "
        f"{', '.join(f'{len(f):,}' for _, f in anim.static)} triangles), an orbiting camera; "
        f"flattened: {flat_tris:,} triangles a frame. Through `scenesort serve`; a frame's "
        "time is the client's: flattening (flattened path), hashing and sending what the "
        "service lacks (HEAD first), the job, and fetching its AO.",
        "",
        "| path | frames timed | total s (for all frames) | median ms/frame | BVH s (jobs) "
        "| render s (jobs) |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for name, t in times.items():
        lines.append(f"| {name} | {len(t)} | {total[name]:.1f} | "
                     f"{1e3 * statistics.median(t):.1f} | {phases[name]['bvh'] * scale[name]:.1f}"
                     f" | {phases[name]['ao'] * scale[name]:.2f} |")
    ratio = total["two levels"] / total["flattened"]
    lines += ["", f"Two levels / flattened, total time: **{ratio:.3f}x** (floor <= "
              f"{FRAMES_FLOOR}: {'met' if ratio <= FRAMES_FLOOR else 'NOT met'}). The "
              f"flattened path ran every {args.flat_every}th frame, interleaved; its total is "
              f"its frames' sum scaled to {args.frames}. What the two-level frames built "
              f"(the jobs' build reports): {refits} refits, {built} builds, "
              f"{sum(r['top_level'] == 'built' for r in reports)} top levels."]
    return lines, {"frames_ratio": ratio}


WAVE_PHASES = 4  # cull: distinct meshes per low-poly shape (a wave each)


def cull_field(anim: Animation, side: int) -> list:
    """`side` x `side` instances 1.3 apart, the grid cut into 4 x 3 regions with a mesh
    each (of 12: three low-poly shapes under four waves), as ((vertices, indices),
    transform) pairs."""
    meshes = [(deform(v, 0.02 * k, float(k)), f) for v, f in anim.static
              for k in range(WAVE_PHASES)]
    rng = np.random.default_rng(3)
    out = []
    for i in range(side):
        for j in range(side):
            angle, scale = rng.uniform(0, 2 * np.pi), rng.uniform(0.6, 1.0)
            c, s_ = np.cos(angle), np.sin(angle)
            m = np.zeros((3, 4), np.float32)
            m[:, :3] = np.array([[c, 0, s_], [0, 1, 0], [-s_, 0, c]]) * scale
            m[:, 3] = (1.3 * (i - side / 2), 0.0, 1.3 * (j - side / 2))
            out.append((meshes[(i * 4 // side) * 3 + j * 3 // side], m))
    return out


def cull_camera(frame: int, frames: int, side: int, size: tuple[int, int]) -> dict:
    """A low camera looking ahead and down, moving along the field's diagonal."""
    reach = 1.3 * side / 2 * 0.8
    t = -reach + 2 * reach * frame / max(frames - 1, 1)
    cam = Camera.look_at((t, 2.5, t - 2.0), (t + 0.5, 0.0, t + 1.0), (0, 1, 0), 50.0, *size,
                         clip_start=0.01, clip_end=1e4)
    return cam.to_dict()


def part_cull(args) -> tuple[list[str], dict]:
    import tempfile
    from pathlib import Path

    from scenesort.backend.render.bundle import BundleWriter
    from scenesort.backend.render.frames import FrameRenderer

    width = args.frame_size
    anim = Animation(1, args.cull_triangles, width, width * 3 // 4)
    placed = cull_field(anim, args.cull_side)
    writer = BundleWriter()
    writer.settings = {"spp": args.frame_spp, "seed": 1, "distance": 0.5}
    for frame in range(args.cull_frames):
        writer.frame(frame, cull_camera(frame, args.cull_frames, args.cull_side, anim.size),
                     placed)
    keys = ("wall", "cpu", "bvh", "bytes", "built", "culled")
    stats: dict[bool, dict[str, list[float]]] = {c: {k: [] for k in keys} for c in (True, False)}
    same = True
    with tempfile.TemporaryDirectory() as tmp:
        bundle = writer.write(Path(tmp))
        renderers = {cull: FrameRenderer(bundle, cull=cull) for cull in (True, False)}
        warm = FrameRenderer(bundle)  # Warp's compile, paid apart
        warm.render(0)
        for frame in range(args.cull_frames):
            images = []
            for cull in ((True, False) if frame % 2 == 0 else (False, True)):
                t0, c0 = time.perf_counter(), time.process_time()
                result = renderers[cull].render(frame)
                row = stats[cull]
                row["wall"].append((time.perf_counter() - t0) * 1e3)
                row["cpu"].append((time.process_time() - c0) * 1e3)
                row["bvh"].append(result.timings_ms.get("bvh", 0.0))
                row["bytes"].append(result.build.bvh_bytes)
                row["built"].append(len(result.build.built) + len(result.build.refit))
                row["culled"].append(result.build.culled)
                images.append(result.ao)
            same &= bool(np.array_equal(*images))
    instances = len(placed)
    meshes = len({id(mesh) for mesh, _ in placed})
    print(f"cull: {instances} instances of {meshes} meshes, {args.cull_frames} frames; images "
          f"the same: {same}")

    def summary(cull: bool) -> dict[str, float]:
        row = stats[cull]
        return {"total_s": sum(row["wall"]) / 1e3, "first_ms": row["wall"][0],
                "median_ms": float(np.median(row["wall"][1:])),
                "cpu_s": sum(row["cpu"]) / 1e3, "bvh_s": sum(row["bvh"]) / 1e3,
                "bytes": float(np.median(row["bytes"])), "peak": max(row["bytes"]),
                "built": sum(row["built"]), "culled": float(np.mean(row["culled"]))}

    on, off = summary(True), summary(False)
    camera_only = cull_decision_costs(args)
    lines = [
        f"Run: `{args.command}`, load average {load()} on {cpu_cores()} cores (shared with "
        "other work: indicative figures; the two paths ran interleaved in one process).",
        "",
        f"A field larger than the view: {instances} instances ({args.cull_side} x "
        f"{args.cull_side}, 1.3 apart) of {meshes} meshes (bunny, dragon, buddha "
        f"vertex-clustered to about {args.cull_triangles:,} triangles, {WAVE_PHASES} waves "
        f"each; a mesh per region of 4 x 3), a low camera moving across it, {args.cull_frames} "
        f"frames {width}x{width * 3 // 4}, spp {args.frame_spp}, AO distance 0.5; "
        "`FrameRenderer` with culling on and off, frame by frame in turn. Images bit for "
        f"bit the same: **{same}**.",
        "",
        "| culling | total s (wall) | CPU s | BVH s | first frame ms | median ms/frame after "
        "| BVH bytes traced (median / peak) | meshes built | instances culled (mean) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
        *(f"| {name} | {r['total_s']:.2f} | {r['cpu_s']:.2f} | {r['bvh_s']:.2f} | "
          f"{r['first_ms']:.0f} | {r['median_ms']:.1f} | {r['bytes'] / 2**20:.2f} / "
          f"{r['peak'] / 2**20:.2f} MiB | {r['built']} | {r['culled']:.0f} |"
          for name, r in (("on", on), ("off", off))),
        "",
        f"The camera-only frame with {args.instances:,} bunny instances (the field of "
        "`--part instances`, a camera moving over it; wall ms, CPU ms of all threads in "
        f"brackets, medians of {camera_only['runs']} interleaved runs; mean "
        f"{camera_only['visible']:.0f} instances in view):",
        "",
        "| step | ms |",
        "|---|---:|",
        *(f"| {name} | {camera_only[key][0]:.2f} ({camera_only[key][1]:.2f}) |"
          for name, key in (("cull decision (`frames.visible`)", "decide"),
                            ("top level over the instances in view", "top_visible"),
                            ("**camera-only frame with culling** (both)", "both"),
                            ("top level over all instances (no culling)", "top_all"))),
    ]
    return lines, {"same": same, "total_ratio": on["total_s"] / off["total_s"],
                   "bytes_ratio": on["bytes"] / off["bytes"]}


def cull_decision_costs(args) -> dict:
    """Per camera over the bunny field: the cull decision, the top level over what is in
    view, and the top level over everything; medians of (wall, CPU) ms."""
    from scenesort.backend.render.visibility import View, visible
    from scenesort.backend.work.store import Store

    bunny = shared_scene("bunny")
    v, f = bunny.vertices, bunny.indices
    bvh = kernels.build_bvh(v, f)
    ts = bunny_field(args.instances, v)
    ids = np.zeros(args.instances, np.int32)
    mesh = wire.SceneArrays(vertices=v, indices=f, scene_id="bunny", degenerate=0)
    scene = wire.InstanceScene("field", (mesh,), ids, ts)
    store = Store(2**30)
    lo, hi = ts[:, :, 3].min(0), ts[:, :, 3].max(0)
    cameras = []
    for k in range(8):
        x = lo[0] + (hi[0] - lo[0]) * (k + 0.5) / 8
        cam = Camera.look_at((x, 0.3, lo[2] - 0.1), (x + 0.05, 0.0, lo[2] + 0.3), (0, 1, 0),
                             50.0, 64, 48, clip_start=0.01, clip_end=1e4)
        cameras.append(View(cam, 0.02))
    visible(store, scene, cameras[0])  # the box, cached as in the frames
    kernels.build_scene([bvh], ids, ts)  # warm-up
    out: dict[str, list[tuple[float, float]]] = {k: [] for k in ("decide", "top_visible",
                                                                 "both", "top_all")}
    seen = []

    def timed(fn):
        t0, c0 = time.perf_counter(), time.process_time()
        value = fn()
        return value, ((time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3)

    for _ in range(args.repeat):
        for view in cameras:
            (keep, placed), decide = timed(lambda view=view: visible(store, scene, view))
            _, top = timed(lambda keep=keep, placed=placed: kernels.build_scene(
                [bvh], ids, ts, visible=keep, placed=placed))
            _, full = timed(lambda: kernels.build_scene([bvh], ids, ts))
            out["decide"].append(decide)
            out["top_visible"].append(top)
            out["both"].append((decide[0] + top[0], decide[1] + top[1]))
            out["top_all"].append(full)
            seen.append(int(keep.sum()))
    result: dict = {k: tuple(np.median(np.array(x), axis=0)) for k, x in out.items()}
    result["runs"] = len(seen)
    result["visible"] = float(np.mean(seen))
    print(f"  camera-only, {args.instances} instances: " + ", ".join(
        f"{k} {x[0]:.2f} ms" for k, x in result.items() if isinstance(x, tuple)))
    return result


PARTS = {"refit": part_refit, "instances": part_instances, "frames": part_frames,
         "cull": part_cull}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=("all", *PARTS), default="all")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--subdivide", type=int, default=2)
    parser.add_argument("--instances", type=int, default=1000)
    parser.add_argument("--flat-instances", type=int, default=256)
    parser.add_argument("--size", type=int, default=384, help="image width (height 3/4)")
    parser.add_argument("--frames", type=int, default=100, help="frames: frames timed")
    parser.add_argument("--frame-instances", type=int, default=200,
                        help="frames: instances of the three static meshes")
    parser.add_argument("--frame-triangles", type=int, default=6000,
                        help="frames: the static meshes vertex-clustered to at least this")
    parser.add_argument("--frame-size", type=int, default=64, help="frames: image width")
    parser.add_argument("--frame-spp", type=int, default=4, help="frames: AO samples")
    parser.add_argument("--flat-every", type=int, default=5,
                        help="frames: the flattened path on every n-th frame (its total scaled)")
    parser.add_argument("--cull-frames", type=int, default=40, help="cull: frames")
    parser.add_argument("--cull-triangles", type=int, default=50000,
                        help="cull: the meshes vertex-clustered to at least this")
    parser.add_argument("--cull-side", type=int, default=30,
                        help="cull: the field's side in instances (side^2 of them)")
    parser.add_argument("--no-docs", action="store_true", help="print only")
    args = parser.parse_args(argv)
    args.command = "python benchmarks/animation.py " + " ".join(argv or sys.argv[1:])
    for name, part in PARTS.items():
        if args.part in ("all", name):
            lines, _ = part(args)
            body = "\n".join(lines)
            print(body)
            if not args.no_docs:
                write_section(f"animation-{name}", f"### `--part {name}`\n\n{body}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
