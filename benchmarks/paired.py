"""Two checkouts of the engine side by side: paired, interleaved timings (the "no slower"
floors of a refactoring).

    .venv/bin/python benchmarks/paired.py --old ../base --new . [--scenes bunny,sponza]
        [--rounds 5] [--repeat 3] [--size 1024] [--small 512] [--what build,trace,...]

Each round starts, for every scene, one process per checkout (in alternating order every
round), each with that checkout's own virtual environment (`<root>/.venv/bin/python`) and
engine; a process warms every measurement up once (compilation excluded), then runs them
--repeat times in turn and reports the median. Per (scene, measurement) it prints the old
and new median of the rounds and the median of the per-round ratios new / old, with every
round's ratio: a ratio is taken between two processes that ran one after the other, so a
burst of load on a shared machine hits both.

Measurements, all through the public API with explicit constants (defaults may differ
between the checkouts): `build` (binned SAH, every core), `trace` (closest hit, the scene's
camera at size x size), `anyhit` (one occlusion ray per primary hit, within 0.1 of the box
diagonal), `dacrt_pool` (RDH, C_SORT 4, 16 rays: the CPU constants), `dacrt_bf`
(breadth-first, alpha 32, beta 128, at small x small), `ao` (8 spp at small x small);
and on one thread (one worker): `build1`, `trace1`, `anyhit1`, `dacrt_pool1` (the tasks
that two workers would sort in one worker likewise), `ao1`. Every figure comes as wall
time and as the process's CPU time (`<what> cpu`): on one thread the CPU time is the
steadiest figure on a shared machine (another process's load does not count in it); with
several workers it also counts the time idle workers spin.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

WHAT = ("build", "trace", "anyhit", "dacrt_pool", "dacrt_bf", "ao")
ONE_THREAD = ("build1", "trace1", "anyhit1", "dacrt_pool1", "ao1")  # also: --what


def measure(args: argparse.Namespace) -> None:
    """Child mode: time one scene with the engine importable from the working directory."""
    from dataclasses import replace

    import numpy as np
    import warp as wp

    wp.config.quiet = True
    # The engine by its import name; an --old checkout may keep the scenes in a flat
    # backend/, or predate the one import name (top-level packages `kernels`, `backend`).
    for engine, where in (("scenesort.kernels", "scenesort.backend.render.scenes"),
                          ("scenesort.kernels", "scenesort.backend.scenes"),
                          ("kernels", "backend.scenes")):
        try:
            kernels, scenes = importlib.import_module(engine), importlib.import_module(where)
            break
        except ImportError:
            continue
    else:
        raise ImportError("no scenesort engine importable from " + os.getcwd())

    scene = scenes.shared_scene(args.scene)
    v, f = scene.vertices, scene.indices
    o, d, tmin, tmax = replace(scene.camera, width=args.size, height=args.size).rays()
    so, sd, stmin, stmax = replace(scene.camera, width=args.small, height=args.small).rays()
    bvh = kernels.build_bvh(v, f)
    h = kernels.trace(bvh, o, d, tmin, tmax)
    hit = h.triangle >= 0
    rng = np.random.default_rng(1)
    w = rng.normal(size=(int(hit.sum()), 3)).astype(np.float32)
    diag = float(np.linalg.norm(bvh.bounds[1] - bvh.bounds[0]))
    p = (o[hit] + h.t[hit, None] * d[hit]).astype(np.float32)
    ao_o = (p + 1e-4 * diag * w / np.linalg.norm(w, axis=1, keepdims=True)).astype(np.float32)
    pool = {"c_sort": 4.0, "min_rays": 16}
    one = {"workers": 1, "small_items": max(32768, (len(o) + len(f)) // 2)}  # as two workers
    jobs = {
        "build1": lambda: kernels.build_bvh(v, f, workers=1),
        "trace1": lambda: kernels.trace(bvh, o, d, tmin, tmax, threads=1),
        "anyhit1": lambda: kernels.trace(bvh, ao_o, w, 0.0, 0.1 * diag, any_hit=True,
                                         threads=1),
        "dacrt_pool1": lambda: kernels.dacrt_trace(v, f, o, d, tmin, tmax, **pool, **one),
        "ao1": lambda: kernels.render_ao(bvh, so, sd, spp=8, tmin=stmin, tmax=stmax, threads=1),
        "build": lambda: kernels.build_bvh(v, f),
        "trace": lambda: kernels.trace(bvh, o, d, tmin, tmax),
        "anyhit": lambda: kernels.trace(bvh, ao_o, w, 0.0, 0.1 * diag, any_hit=True),
        "dacrt_pool": lambda: kernels.dacrt_trace(v, f, o, d, tmin, tmax, c_sort=4.0,
                                                  min_rays=16),
        "dacrt_bf": lambda: kernels.dacrt_trace(v, f, so, sd, stmin, stmax,
                                                variant="breadth_first", alpha=32, beta=128),
        "ao": lambda: kernels.render_ao(bvh, so, sd, spp=8, tmin=stmin, tmax=stmax),
    }
    what = args.what.split(",")
    for name in what:
        jobs[name]()
    ms: dict[str, list[float]] = {name: [] for name in what}
    cpu: dict[str, list[float]] = {name: [] for name in what}
    for _ in range(args.repeat):
        for name in what:
            c0, t0 = time.process_time(), time.perf_counter()
            jobs[name]()
            ms[name].append((time.perf_counter() - t0) * 1e3)
            cpu[name].append((time.process_time() - c0) * 1e3)
    out = {name: statistics.median(x) for name, x in ms.items()}
    out.update({f"{name} cpu": statistics.median(x) for name, x in cpu.items()})
    print(json.dumps(out))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--old", type=Path, required=False)
    p.add_argument("--new", type=Path, default=Path(__file__).resolve().parents[1])
    p.add_argument("--scenes", default="bunny,dragon,buddha,blade,sponza,sibenik,conference")
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--size", type=int, default=1024)
    p.add_argument("--small", type=int, default=512)
    p.add_argument("--what", default=",".join(WHAT))
    p.add_argument("--log", type=Path, help="append every process's figures here (JSON lines)")
    p.add_argument("--scene", help=argparse.SUPPRESS)  # child mode
    args = p.parse_args()
    if args.scene:
        measure(args)
        return 0
    if args.old is None:
        p.error("--old is required")
    child = [str(Path(__file__).resolve()), "--size", str(args.size), "--small",
             str(args.small), "--repeat", str(args.repeat), "--what", args.what]
    # numpy's BLAS threads spin after a call: one thread, so CPU times are the engine's
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1",
           "MKL_NUM_THREADS": "1"}
    rounds: dict[tuple[str, str], list[tuple[float, float]]] = {}
    for r in range(args.rounds):
        for scene in args.scenes.split(","):
            got = {}
            order = [("old", args.old), ("new", args.new)]
            for tag, root in order if r % 2 == 0 else order[::-1]:
                root = root.resolve()
                proc = subprocess.run([str(root / ".venv/bin/python"), *child, "--scene", scene],
                                      cwd=root, capture_output=True, text=True, env=env)
                lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
                if proc.returncode != 0 or not lines:
                    print(proc.stderr[-3000:], file=sys.stderr)
                    return 1
                got[tag] = json.loads(lines[-1])
                if args.log:
                    with args.log.open("a") as log:
                        log.write(json.dumps({"round": r, "scene": scene, "tag": tag,
                                              "ms": got[tag]}) + "\n")
            for name in got["old"]:
                rounds.setdefault((scene, name), []).append((got["old"][name], got["new"][name]))
            print(f"round {r + 1}/{args.rounds}: {scene}", file=sys.stderr, flush=True)
    print(f"{'scene':11s} {'what':11s} {'old ms':>9s} {'new ms':>9s} {'new/old':>8s}  rounds")
    for (scene, name), pairs in rounds.items():
        old = statistics.median(a for a, _ in pairs)
        new = statistics.median(b for _, b in pairs)
        ratios = [b / a for a, b in pairs]
        print(f"{scene:11s} {name:11s} {old:9.1f} {new:9.1f} {statistics.median(ratios):8.3f}  "
              + " ".join(f"{x:.3f}" for x in ratios))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
