"""Camera rays through a two-level scene as packets (kernels/scene/packet.py) against ray by
ray, and the filtered film through the scene against the same scene flattened into one mesh.

    .venv/bin/python benchmarks/scene_packets.py [--repeat 5] [--size 320x240]

The scene is generated: six copies of the shared dragon, each turned about the up axis by its
own angle, each its own mesh and instance (as the add-on sends objects), on a ground grid of
80,000 triangles, seen from above at 50 degrees. Rows: `kernels.trace` of 64 rays a pixel
(spread over a pixel, as the film's filtered samples) through pixels on a 4-pixel grid,
packets against ray by ray on 1 and on 2 host threads (MRays/s, medians of interleaved runs
after a warm-up; rays whose hits differ), and `render_film` (Blackman-Harris 1.5 px, 64 spp)
through the two-level scene and through the flattened mesh, 1 thread (seconds). Prints a
table; nothing is written to docs/.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scenesort.backend.render.scenes import load_mesh, shared_scenes_dir  # noqa: E402

from scenesort import kernels  # noqa: E402


def gallery() -> tuple[list, np.ndarray, kernels.Camera]:
    """((vertices, indices) per mesh, (I, 3, 4) transforms, camera) of the scene above."""
    v, f = load_mesh(shared_scenes_dir() / "dragon.ply")
    v = v - v.mean(axis=0)
    v = (v / np.abs(v).max()).astype(np.float32)
    floor = float(v[:, 1].min())
    xs = np.linspace(-6.0, 6.0, 201)
    gx, gz = np.meshgrid(xs, xs)
    gv = np.stack([gx.ravel(), np.full(gx.size, floor), gz.ravel()], axis=1).astype(np.float32)
    idx = np.arange(gx.size).reshape(gx.shape)
    a, b, c, d = (idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(),
                  idx[1:, 1:].ravel())
    gf = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)]).astype(np.int32)
    transforms = []
    for k in range(6):
        angle = 0.9 * k
        rot = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0],
                        [-np.sin(angle), 0, np.cos(angle)]])
        shift = [(k % 3 - 1) * 2.2, 0.0, (k // 3 - 0.5) * 2.2]
        transforms.append(np.hstack([rot, np.array(shift)[:, None]]))
    transforms.append(np.eye(3, 4))
    camera = kernels.Camera.look_at(np.array([0.0, 2.5, 5.5]), np.array([0.0, floor + 0.3, 0.0]),
                                    (0, 1, 0), 50.0, 320, 240, clip_start=0.0, clip_end=1e10)
    return [(v, f)] * 6 + [(gv, gf)], np.array(transforms, np.float32), camera


def flatten(meshes, transforms) -> tuple[np.ndarray, np.ndarray]:
    verts, faces, base = [], [], 0
    for (mv, mf), t in zip(meshes, transforms, strict=True):
        w = mv.astype(np.float64) @ t[:, :3].astype(np.float64).T + t[:, 3]
        verts.append(w.astype(np.float32))
        faces.append(mf + base)
        base += len(mv)
    return np.vstack(verts), np.vstack(faces)


def timed(fns: dict, repeat: int) -> dict[str, float]:
    """Median seconds of each function, interleaved, after one warm-up call each."""
    times: dict[str, list[float]] = {k: [] for k in fns}
    for rnd in range(repeat + 1):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            if rnd:
                times[name].append(time.perf_counter() - t0)
    return {k: statistics.median(v) for k, v in times.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    meshes, transforms, camera = gallery()
    scene = kernels.build_scene([kernels.build_bvh(v, f) for v, f in meshes],
                                np.arange(len(meshes)), transforms)
    flat = kernels.build_bvh(*flatten(meshes, transforms))
    o, d, _, _ = camera.rays()
    pick = np.arange(len(o)).reshape(camera.height, camera.width)[::4, ::4].ravel()
    rng = np.random.default_rng(0)
    po = np.repeat(o[pick], 64, axis=0)
    spread = float(np.linalg.norm(d[1] - d[0]))
    pd = (np.repeat(d[pick], 64, axis=0)
          + rng.uniform(-spread, spread, (len(po), 3))).astype(np.float32)
    a, b = (kernels.trace(scene, po, pd, packets=p) for p in (True, False))
    differ = int((~((a.t == b.t) & (a.triangle == b.triangle) & (a.instance == b.instance)
                    & (a.u == b.u) & (a.v == b.v))).sum())
    tris = sum(len(f) for _, f in meshes)
    print(f"gallery: {len(meshes)} instances, {tris:,} triangles; {len(po):,} camera rays "
          f"(64 a pixel); rays whose hits differ between packets and ray by ray: {differ}")
    print("| rays | threads | ray by ray MRays/s | packets MRays/s | ratio |")
    print("|---|---:|---:|---:|---:|")
    for threads in (1, 2):
        t = timed({p: (lambda p=p, n=threads: kernels.trace(scene, po, pd, threads=n, packets=p))
                   for p in (False, True)}, args.repeat)
        print(f"| camera, 64 a pixel | {threads} | {len(po) / t[False] / 1e6:.2f} | "
              f"{len(po) / t[True] / 1e6:.2f} | {t[False] / t[True]:.2f} |")
    film = {"spp": 64, "filter_width": 1.5, "threads": 1}
    t = timed({"scene": lambda: kernels.render_film(scene, camera, **film),
               "flat": lambda: kernels.render_film(flat, camera, **film)}, max(2, args.repeat // 2))
    print(f"\nfilm {camera.width}x{camera.height}, 64 spp, Blackman-Harris 1.5 px, 1 thread: "
          f"two-level scene {t['scene']:.3f} s, flattened mesh {t['flat']:.3f} s "
          f"({t['scene'] / t['flat']:.2f}x)")


if __name__ == "__main__":
    main()
