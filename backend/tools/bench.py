"""`scenesort bench`: build and trace one scene with the engine and its peers, in one run.

A quick look, not the papers' tables (those are `benchmarks/bvh.py`): build ms and SAH cost
for both methods, then MRays/s for camera rays (closest hit) and AO rays (any hit) against
Warp's `wp.Mesh` and, when `embreex` is installed, Embree.
"""

from __future__ import annotations

import argparse

from rich.console import Console
from rich.table import Table


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", default=None,
                        help="a mesh file or a shared scene name (default: the built-in scene)")
    parser.add_argument("--width", type=int, default=512)
    parser.add_argument("--height", type=int, default=384)
    parser.add_argument("--repeat", type=int, default=3, help="timed runs (median reported)")
    parser.add_argument("--threads", type=int, default=None, help="host threads (default: all)")


def run(args: argparse.Namespace) -> int:
    import numpy as np
    from scenesort.backend.render.scenes import load_scene
    from scenesort.backend.tools import peers
    from scenesort.kernels.core import cpu_cores
    from scenesort.kernels.render import default_distance

    from scenesort import kernels

    console = Console()
    scene = load_scene(args.scene, args.width, args.height)
    v, f = scene.vertices, scene.indices
    threads = args.threads or cpu_cores()
    console.print(f"[bold]{scene.name}[/]: {len(f):,} triangles, {args.width}x{args.height} "
                  f"camera rays, {threads} thread(s), median of {args.repeat}")

    builds = Table("BVH build", "ms", "SAH cost", "nodes", "ours / wp.Mesh")
    bvhs = {}
    first = kernels.build_bvh(np.eye(3, dtype=np.float32), np.array([[0, 1, 2]], np.int32))
    builds.add_row("compile (Warp, first use; not in the rows below)",
                   f"{first.stats.compile_ms:.1f}", "", "", "")
    for method in ("sah", "median"):
        t = peers.timeit(lambda m=method: bvhs.__setitem__(m, kernels.build_bvh(v, f, m)),
                         args.repeat)
        ref = peers.timeit(lambda m=method: peers.WarpMesh(v, f, m, 8), args.repeat)
        s = bvhs[method].stats
        builds.add_row(f"ours {method}", f"{1e3 * t:.1f}", f"{s.sah_cost:.1f}",
                       f"{s.nodes:,}", f"{t / ref:.2f}")
        builds.add_row(f"wp.Mesh {method} (leaf 8)", f"{1e3 * ref:.1f}", "", "", "")
    console.print(builds)

    bvh = bvhs["sah"]
    o, d, tmin, tmax = scene.camera.rays()
    hits = kernels.trace(bvh, o, d, tmin, tmax)
    ao_o, ao_d = peers.ao_rays(v, f, o, d, hits.t, hits.triangle)
    dist = default_distance(bvh)
    tracers = [("wp.Mesh", peers.WarpMesh(v, f, "sah"))]
    if peers.embree_available():
        tracers.append(("Embree (1 thread)", peers.Embree(v, f)))
    traces = Table("rays", "count", "ours MRays/s", *(f"{n} MRays/s" for n, _ in tracers),
                   *(f"ours / {n}" for n, _ in tracers))
    for label, (ro, rd, limit, any_hit) in {
        "camera (closest)": (o, d, 1e30, False),
        "AO (any hit)": (ao_o, ao_d, dist, True),
    }.items():
        ours = peers.timeit(lambda ro=ro, rd=rd, lim=limit, a=any_hit: kernels.trace(
            bvh, ro, rd, tmax=lim, any_hit=a, threads=threads), args.repeat)
        theirs = [peers.timeit((lambda p=p, ro=ro, rd=rd, lim=limit: p.occluded(ro, rd, lim,
                                                                               threads))
                               if any_hit else
                               (lambda p=p, ro=ro, rd=rd: p.closest(ro, rd, 1e30, threads)),
                               args.repeat) for _, p in tracers]
        n = len(ro)
        traces.add_row(label, f"{n:,}", f"{n / ours / 1e6:.2f}",
                       *(f"{n / t / 1e6:.2f}" for t in theirs),
                       *(f"{t / ours:.2f}" for t in theirs))
    console.print(traces)
    return 0
