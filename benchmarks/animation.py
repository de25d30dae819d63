"""Scenes that change (issue 18): refit against rebuild, and instances against the flattened
scene, with the issue's floors.

    python benchmarks/animation.py [--part refit|instances|all] [--repeat 3] [--no-docs]
        [--subdivide 2] [--instances 1000] [--flat-instances 64] [--size 384]

refit: the bunny subdivided `--subdivide` times (4x triangles each: 2 -> 1.1 M) and deformed
  by a smooth wave, frame after frame: `refit_bvh` of the deformed mesh against `build_bvh`
  of it (same options, every core), medians of interleaved runs after a warm-up. Then the
  rebuild rule's measurement: for growing deformations, the refit tree's SAH ratio and its
  trace time (camera rays, closest hit) against a fresh build's.
instances: `--instances` bunnies (rotated, scaled, on a grid): the scene's device bytes
  against one bunny's plus the top level's; trace speed (camera rays closest hit, and AO)
  of the two-level scene against the flattened one at `--flat-instances` (flattening 1,000
  bunnies, 69 M triangles, does not fit this machine's memory beside the others' work).
Warp's compile time is paid in the warm-up and not counted. Writes its sections of
docs/benchmarks.md ("Dynamic scenes"), marked as measured on a loaded machine.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
import trimesh
import warp as wp

wp.config.quiet = True

from docs_section import write_section  # noqa: E402  (benchmarks/ is on sys.path)

import kernels  # noqa: E402
from backend.scenes import shared_scene  # noqa: E402
from kernels.core import cpu_cores  # noqa: E402
from kernels.render import default_distance  # noqa: E402
from kernels.scene import bvh_nbytes  # noqa: E402

REFIT_FLOOR = 0.3  # refit time / rebuild time, at most
MEMORY_FLOOR = 1.1  # scene bytes / (one bunny + top level), at most
TRACE_FLOOR = 0.7  # two-level trace speed / flattened, at least
WAVES = (0.0, 0.01, 0.02, 0.05, 0.1, 0.2, 0.4)  # deformation amplitudes, of the box diagonal


def median_ms(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(times))


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
    phases = out.stats["phase_ms"]
    rows = []
    for amount in WAVES:
        frame = deform(v, amount, 1.0)
        refit_tree = kernels.build_bvh(v, f)
        refit_tree = kernels.refit_bvh(refit_tree, frame, rebuild_ratio=np.inf)
        fresh = kernels.build_bvh(frame, f)
        kernels.trace(fresh, o, d, tmin, tmax)
        tr = median_ms(lambda t=refit_tree: kernels.trace(t, o, d, tmin, tmax), args.repeat)
        tf = median_ms(lambda t=fresh: kernels.trace(t, o, d, tmin, tmax), args.repeat)
        rows.append({"amount": amount, "sah_ratio": refit_tree.stats["sah_ratio"],
                     "fresh_ratio": fresh.stats["sah_cost"] / refit_tree.stats["build_sah_cost"],
                     "trace_ratio": tr / tf})
        print(f"  wave {amount:5.2f}: SAH refit/built {rows[-1]['sah_ratio']:.3f}, fresh/built "
              f"{rows[-1]['fresh_ratio']:.3f}, trace refit/fresh {tr / tf:.3f}")
    ratio = refit_ms / rebuild_ms
    lines = [
        f"Run: `{args.command}`, load average {load()} on {cpu_cores()} cores (shared with "
        "other work: indicative figures; the ratios are of the same run).",
        "",
        f"Refit of the bunny subdivided {args.subdivide}x ({len(f):,} triangles, width "
        f"{bvh.stats['width']}) under a smooth wave (1% of the diagonal), frame after frame, "
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
        f"growing amplitude; closest-hit camera rays ({len(o):,}) through the refit tree "
        "against a fresh build of the deformed mesh.",
        "",
        "| wave (x diagonal) | SAH refit / built | SAH fresh / built | trace refit / fresh |",
        "|---:|---:|---:|---:|",
        *(f"| {r['amount']:.2f} | {r['sah_ratio']:.3f} | {r['fresh_ratio']:.3f} | "
          f"{r['trace_ratio']:.3f} |" for r in rows),
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
        kernels.render_ao(t, o, d, 1, dist, tmin=tmin, tmax=tmax)
    out: dict[str, list[float]] = {f"{k} {w}": [] for k in tracers for w in ("trace", "ao")}
    for _ in range(args.repeat):
        for k, t in tracers.items():
            out[f"{k} trace"].append(median_ms(lambda t=t: kernels.trace(t, o, d, tmin, tmax), 1))
            out[f"{k} ao"].append(median_ms(
                lambda t=t: kernels.render_ao(t, o, d, 4, dist, tmin=tmin, tmax=tmax), 1))
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
        f"| one bunny (BVH width {bvh.stats['width']} and mesh) | {one / 2**20:.2f} |",
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
        f"{args.instances * flat_bytes_per_bunny / 2**30:.0f} GiB: more than this machine "
        "spares), and the two-level scene alone at the full count.",
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


PARTS = {"refit": part_refit, "instances": part_instances}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=("all", *PARTS), default="all")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--subdivide", type=int, default=2)
    parser.add_argument("--instances", type=int, default=1000)
    parser.add_argument("--flat-instances", type=int, default=64)
    parser.add_argument("--size", type=int, default=384, help="image width (height 3/4)")
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
