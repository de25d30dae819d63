"""A frame bundle rendered in one process and on a local Ray cluster, in the same run.

    .venv/bin/python benchmarks/frames.py [--frames 48] [--width 320 --height 240] [--spp 64]
                                          [--rounds 1] [--no-docs]

The bundle: the shared bunny, dragon and Happy Buddha as 12 instances on a floor, one more
bunny deformed by a travelling wave in every frame (a new mesh per frame, as an armature or
a simulation gives), and a camera orbiting the group. It is rendered three ways: one
process with one engine thread, one process with every core, and a local Ray cluster of two
one-CPU workers (one engine thread per frame). Every way renders the same 2 warm-up frames
first (Warp's kernels loaded, the cluster's workers started) and the cluster's start-up is
timed apart. Floors: the cluster at least 1.6x faster than one process on one thread,
and within 1.15x of one process on both cores; bytes sent per frame after the first
are the changed transforms and meshes only. Writes the frames section of docs/benchmarks.md
unless --no-docs.
"""

from __future__ import annotations

import argparse
import math
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from scenesort.backend.render.bundle import BundleWriter  # noqa: E402
from scenesort.backend.render.cluster import connect, import_ray, render_frames_ray  # noqa: E402
from scenesort.backend.render.frames import render_frames  # noqa: E402
from scenesort.backend.render.scenes import load_mesh, shared_scenes_dir  # noqa: E402

from benchmarks.docs_section import write_section  # noqa: E402

WARM_UP = 2
MESHES = ("bunny", "dragon", "buddha")


def unit_mesh(name: str) -> tuple[np.ndarray, np.ndarray]:
    """A shared scene mesh centred on x/z, resting on y=0, 1 unit tall."""
    folder = shared_scenes_dir()
    if folder is None:
        raise SystemExit("no shared scenes folder: set $SCENESORT_SCENES")
    v, f = load_mesh(folder / f"{name}.ply")
    lo, hi = v.min(0), v.max(0)
    v = (v - np.float32([(lo[0] + hi[0]) / 2, lo[1], (lo[2] + hi[2]) / 2])) / (hi[1] - lo[1])
    return v.astype(np.float32), f


def floor(size: float) -> tuple[np.ndarray, np.ndarray]:
    s = size / 2
    v = np.float32([[-s, 0, -s], [s, 0, -s], [s, 0, s], [-s, 0, s]])
    return v, np.int32([[0, 2, 1], [0, 3, 2]])


def placed(x: float, z: float, turn: float = 0.0, scale: float = 1.0) -> np.ndarray:
    c, s = math.cos(turn) * scale, math.sin(turn) * scale
    return np.float32([[c, 0, s, x], [0, scale, 0, 0], [-s, 0, c, z]])


def orbit_camera(angle: float, width: int, height: int) -> dict:
    """Blender's camera wire form: on a circle around the group, looking at its centre."""
    eye = np.array([7.0 * math.sin(angle), 3.0, 7.0 * math.cos(angle)])
    back = eye - np.array([0.0, 0.5, 0.0])
    back /= np.linalg.norm(back)
    right = np.cross([0.0, 1.0, 0.0], back)
    right /= np.linalg.norm(right)
    matrix = np.eye(4)
    matrix[:3, 0], matrix[:3, 1], matrix[:3, 2], matrix[:3, 3] = (
        right, np.cross(back, right), back, eye)
    return {"matrix_world": matrix.tolist(), "width": width, "height": height,
            "clip_start": 0.01, "clip_end": 100.0}


def make_bundle(root: Path, frames: int, width: int, height: int, spp: int) -> Path:
    meshes = {name: unit_mesh(name) for name in MESHES}
    ground = floor(12.0)
    writer = BundleWriter(settings={"spp": spp, "seed": 7, "distance": 1.0})
    bunny_v, bunny_f = meshes["bunny"]
    for k in range(WARM_UP + frames):
        phase = 0.4 * k
        wave = bunny_v.copy()
        wave[:, 0] += 0.06 * np.sin(8.0 * bunny_v[:, 1] + phase)
        scene = [(ground, placed(0, 0))]
        for j in range(12):
            a = 2 * math.pi * j / 12
            scene.append((meshes[MESHES[j % 3]], placed(3.5 * math.cos(a), 3.5 * math.sin(a),
                                                        turn=a + 0.05 * k)))
        scene.append(((wave, bunny_f), placed(0, 0, scale=1.5)))
        writer.frame(k + 1, orbit_camera(0.05 * k, width, height), scene)
    return writer.write(root)


def timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=48)
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--rounds", type=int, default=1)
    parser.add_argument("--no-docs", action="store_true")
    args = parser.parse_args()
    ray = import_ray()
    work = Path(tempfile.mkdtemp(prefix="scenesort-frames-"))
    bundle = make_bundle(work / "bundle", args.frames, args.width, args.height, args.spp)
    warm = list(range(1, WARM_UP + 1))
    timed_frames = list(range(WARM_UP + 1, WARM_UP + args.frames + 1))
    startup = connect(ray, "local", 2)
    out = {name: work / name for name in ("one", "both", "ray")}

    def one_process(threads: int | None, folder: Path) -> float:
        shutil.rmtree(folder, ignore_errors=True)
        render_frames(bundle, folder, frames=warm, threads=threads, progress=False)
        return timed(lambda: render_frames(bundle, folder, frames=timed_frames,
                                           threads=threads, progress=False))

    def cluster(folder: Path):
        shutil.rmtree(folder, ignore_errors=True)
        render_frames_ray(bundle, folder, frames=warm, threads=1)
        run = render_frames_ray(bundle, folder, frames=timed_frames, threads=1)
        if run.failed:
            raise SystemExit(f"frames failed on the cluster: {run.failed}")
        return run

    times: dict[str, list[float]] = {"one": [], "both": [], "ray": []}
    run = None
    for r in range(args.rounds):  # interleaved: each round runs every way once
        times["one"].append(one_process(1, out["one"]))
        times["both"].append(one_process(None, out["both"]))
        run = cluster(out["ray"])
        times["ray"].append(run.render_s)
        print(f"round {r + 1}: " + ", ".join(f"{k} {v[-1]:.1f} s" for k, v in times.items()))
    ray.shutdown()
    same = all((out["one"] / f"{n:06d}.npy").read_bytes() == (out["ray"] / f"{n:06d}.npy")
               .read_bytes() for n in timed_frames)
    med = {k: statistics.median(v) for k, v in times.items()}
    after_first = [run.sent_bytes[n] for n in timed_frames[1:]]
    bunny_v, bunny_f = unit_mesh("bunny")
    deformed = bunny_v.nbytes + bunny_f.nbytes
    returned = statistics.median(run.returned_bytes.values())
    rows = [
        ("one process, 1 engine thread", med["one"], med["one"] / args.frames, 1.0),
        ("one process, both cores", med["both"], med["both"] / args.frames,
         med["one"] / med["both"]),
        ("Ray, 2 workers x 1 thread", med["ray"], med["ray"] / args.frames,
         med["one"] / med["ray"]),
    ]
    lines = [
        f"{args.frames} frames ({args.width}x{args.height}, {args.spp} spp; 12 instances of "
        "3 shared meshes, one deforming bunny, an orbiting camera), median of "
        f"{args.rounds} interleaved round(s) after {WARM_UP} warm-up frames each:",
        "",
        "| run | total s | s per frame | speed-up vs one thread |",
        "|---|---:|---:|---:|",
        *(f"| {name} | {total:.1f} | {per:.2f} | {speed:.2f}x |"
          for name, total, per, speed in rows),
        "",
        f"- Ray cluster start-up (ray.init, 2 local workers), apart: {startup:.1f} s.",
        f"- Cluster vs one thread: {med['one'] / med['ray']:.2f}x faster (floor 1.6x: "
        f"{'met' if med['one'] / med['ray'] >= 1.6 else 'NOT met'}); vs both cores: "
        f"{med['ray'] / med['both']:.2f}x the time (floor at most 1.15x: "
        f"{'met' if med['ray'] / med['both'] <= 1.15 else 'NOT met'}).",
        f"- Bytes sent per frame after the first: median {statistics.median(after_first):,.0f}"
        f" (min {min(after_first):,}, max {max(after_first):,}); the deformed bunny is "
        f"{deformed:,} of them, the rest the frame's view, instance list and mesh ids.",
        f"- Returned per frame (AO, coverage, depth float32 and the PNG): {returned:,.0f} "
        "bytes.",
        f"- The driver's work per frame (read and hash-check the bundle's meshes, put them, "
        f"submit): {1e3 * run.submit_s / args.frames:.1f} ms.",
        f"- Cluster frames equal the one-process frames bit for bit: {same}.",
    ]
    text = "\n".join(lines)
    print(text)
    if not args.no_docs:
        write_section("frames", "## Frames on a Ray cluster (benchmarks/frames.py)\n\n"
                      f"`{' '.join(['benchmarks/frames.py', *sys.argv[1:]])}`\n\n" + text)
        print("wrote the frames section of docs/benchmarks.md")
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
