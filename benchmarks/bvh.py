"""The 2012 paper's Tables 6.1/6.2 on the shared scenes: BVH build and trace, against
Warp's `wp.Mesh` and Embree in the same run; and the wide BVH against the binary
one and Embree side by side (`--part wide` runs only that); and ours against embreex on the
same number of threads, a column per thread count, at several batch sizes
(`--part threads` runs only that); and the per-ray speed of small calls against one call of
1M rays (`--part calls`); and camera rays as packets against ray by ray (`--part packets`).

    python benchmarks/bvh.py [--scenes bunny,sponza] [--repeat 5] [--width 1024 --height 768]
    python benchmarks/bvh.py --part wide --width 1024 --height 1024
    python benchmarks/bvh.py --part wide --target-cpu x86-64 --no-docs   # a CPU without AVX2
    python benchmarks/bvh.py --part threads [--batches 256,512,1024]
    python benchmarks/bvh.py --part calls --scenes bunny,conference [--calls 10000,100000]
    python benchmarks/bvh.py --part packets [--repeat 5]

Times are medians of `--repeat` runs after one warm-up. Warp's kernel compile time is
measured once, in a fresh kernel cache, and reported on its own. Writes the tables into
docs/benchmarks.md (between the bvh markers) and the raw figures to docs/figures/bvh.json.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import warp as wp
from rich.console import Console
from rich.markdown import Markdown

ROOT = Path(__file__).resolve().parents[1]
FIGURES = ROOT / "docs" / "figures"
wp.config.kernel_cache_dir = tempfile.mkdtemp(prefix="scenesort-bench-cache-")
wp.config.quiet = True

from docs_section import write_section  # noqa: E402  (benchmarks/ is on sys.path)
from embree_threads import ThreadedEmbree  # noqa: E402
from scenesort.backend.render.scenes import shared_scene, shared_scene_infos  # noqa: E402
from scenesort.backend.tools import peers  # noqa: E402
from scenesort.kernels.core import cpu_cores  # noqa: E402
from scenesort.kernels.core.compile_options import cpu_target_flags  # noqa: E402
from scenesort.kernels.render import default_distance  # noqa: E402

from scenesort import kernels  # noqa: E402

LEAVES = (8, 16, 32)
METHODS = ("sah", "median")
WIDE_WIDTHS = (2, 4, 8)  # 2: the binary tree
AO_PER_HIT = 4  # the wide-BVH floors' AO rays: 4 cosine rays per hit, tmax 0.1 x diagonal
BATCHES = (256, 512, 1024)  # --part threads: square batches of camera rays
CALLS = (10_000, 100_000)  # --part calls: rays per call, against one call of CALL_RAYS
CALL_RAYS = 1 << 20


def compile_seconds() -> dict[str, float]:
    """First-use cost of each engine module in an empty kernel cache."""
    from scenesort.kernels.bvh import build, traversal, wide

    out = {}
    for name, module in (("bvh_build", build.build_worker.module),
                         ("bvh_trace", traversal.trace_kernel.module),
                         ("bvh_collapse", wide.collapse_kernel.module)):
        start = time.perf_counter()
        wp.load_module(module, device="cpu")
        out[name] = time.perf_counter() - start
    return out


def wp_mesh_sah_cost(vertices: np.ndarray, indices: np.ndarray, leaf: int) -> float:
    """SAH cost of the tree `wp.Mesh(bvh_constructor="sah")` builds on CPU, by replaying its
    algorithm (warp/native/bvh.cpp: 16 buckets on the longest centroid axis, partition by
    `centroid < split`, midpoint fallback) in numpy: Warp does not expose its nodes."""
    tri = vertices[indices]
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    centre = 0.5 * (lo + hi)

    def area(a: np.ndarray, b: np.ndarray) -> float:
        e = np.maximum(b.astype(np.float64) - a, 0.0)
        return float(e[0] * e[1] + e[1] * e[2] + e[2] * e[0])

    total = 0.0
    root_area = area(lo.min(axis=0), hi.max(axis=0))
    stack = [(np.arange(len(indices)), 0)]
    while stack:
        ids, depth = stack.pop()
        n = len(ids)
        a = area(lo[ids].min(axis=0), hi[ids].max(axis=0))
        if n <= leaf or depth >= 31:
            total += a * n
            continue
        total += a
        c = centre[ids]
        clo, chi = c.min(axis=0), c.max(axis=0)
        axis = int(np.argmax(chi - clo))
        left = ids[:0]
        if chi[axis] > clo[axis]:
            b = np.clip((16 * (c[:, axis] - clo[axis]) / (chi[axis] - clo[axis])).astype(int),
                        0, 15)
            costs = []
            for s in range(15):
                m = b <= s
                if m.all() or not m.any():
                    costs.append(np.inf)
                    continue
                costs.append(area(lo[ids[m]].min(0), hi[ids[m]].max(0)) * m.sum()
                             + area(lo[ids[~m]].min(0), hi[ids[~m]].max(0)) * (~m).sum())
            best = int(np.argmin(costs))
            split = np.float32(clo[axis] + (best + 1) * (chi[axis] - clo[axis]) / 16)
            left = ids[c[:, axis] < split]
        if len(left) in (0, n):
            stack += [(ids[: n // 2], depth + 1), (ids[n // 2:], depth + 1)]
        else:
            stack += [(left, depth + 1), (ids[c[:, axis] >= split], depth + 1)]
    return total / root_area


def build_rows(name: str, v: np.ndarray, f: np.ndarray, repeat: int) -> tuple[list, dict]:
    rows = []
    for method in METHODS:
        for leaf in LEAVES:
            built = {}

            def run(workers, method=method, leaf=leaf, built=built):
                built["bvh"] = kernels.build_bvh(v, f, method=method, leaf_size=leaf,
                                                 workers=workers)

            ms_all, ms_one, peer_ms, peer_default_ms = (1e3 * x for x in peers.timeit_each([
                lambda run=run: run(None), lambda run=run: run(1),
                lambda method=method, leaf=leaf: peers.WarpMesh(v, f, method, leaf),
                lambda method=method: peers.WarpMesh(v, f, method)], repeat))
            s = built["bvh"].stats
            rows.append({"scene": name, "method": method, "leaf": leaf, "ms_all": ms_all,
                         "ms_one": ms_one, "mtris_s": len(f) / ms_all / 1e3,
                         "sah": s.sah_cost, "nodes": s.nodes, "depth": s.depth,
                         "phase_ms": s.phase_ms, "wp_mesh_ms": peer_ms,
                         "wp_mesh_default_ms": peer_default_ms})
    peer_build = {}
    for c in peers.MESH_CONSTRUCTORS:  # as users call it: default leaf size (4)
        peer_build[f"wp.Mesh {c}"] = 1e3 * peers.timeit(
            lambda c=c: peers.WarpMesh(v, f, c), repeat)
    if peers.embree_available():
        peer_build["Embree"] = 1e3 * peers.timeit(lambda: peers.Embree(v, f), max(1, repeat // 2))
    peer_build["wp.Mesh sah cost (leaf 8)"] = wp_mesh_sah_cost(v, f, 8)
    peer_build["wp.Mesh sah cost (leaf 4)"] = wp_mesh_sah_cost(v, f, 4)  # its default
    return rows, peer_build


def trace_rows(name: str, scene, repeat: int, width: int, height: int) -> list[dict]:
    """MRays/s for each ray kind through our BVH (both methods, leaf 8) and `wp.Mesh` built
    with the same method at its default leaf size; Embree once per ray kind."""
    v, f = scene.vertices, scene.indices
    cam = type(scene.camera).from_dict({**scene.camera.to_dict(), "width": width,
                                        "height": height})
    o, d, _, _ = cam.rays()
    sah = kernels.build_bvh(v, f)
    embree = peers.Embree(v, f) if peers.embree_available() else None
    hits = kernels.trace(sah, o, d)
    dist = default_distance(sah)
    ao_o, ao_d = peers.ao_rays(v, f, o, d, hits.t, hits.triangle, per_hit=7)
    rand_o, rand_d = peers.random_rays(sah.bounds, len(o))  # as many as primary (paper)
    kinds = {
        "primary": (o, d, 1e30, False),
        "AO (7/hit)": (ao_o, ao_d, dist, True),
        "random": (rand_o, rand_d, 1e30, False),
    }
    cores = cpu_cores()
    out = []
    for method in METHODS:
        bvh = sah if method == "sah" else kernels.build_bvh(v, f, method=method)
        mesh = peers.WarpMesh(v, f, method)
        for kind, (ro, rd, tmax, any_hit) in kinds.items():
            row = {"scene": name, "bvh": method, "rays": kind, "count": len(ro)}
            for threads, key in ((1, "1t"), (cores, f"{cores}t")):
                ours = peers.timeit(lambda t=threads, ro=ro, rd=rd, tmax=tmax, a=any_hit, b=bvh:
                                    kernels.trace(b, ro, rd, tmax=tmax, any_hit=a, threads=t),
                                    repeat)
                theirs = peers.timeit(
                    (lambda t=threads, ro=ro, rd=rd, tmax=tmax, m=mesh:
                     m.occluded(ro, rd, tmax, t)) if any_hit else
                    (lambda t=threads, ro=ro, rd=rd, m=mesh: m.closest(ro, rd, 1e30, t)),
                    repeat)
                row[f"ours {key}"] = len(ro) / ours / 1e6
                row[f"wp.Mesh {key}"] = len(ro) / theirs / 1e6
            if embree is not None and method == "sah":
                t = peers.timeit((lambda ro=ro, rd=rd, tmax=tmax: embree.occluded(ro, rd, tmax))
                                 if any_hit else (lambda ro=ro, rd=rd: embree.closest(ro, rd)),
                                 max(1, repeat // 2))
                row["Embree 1t"] = len(ro) / t / 1e6
                ours = kernels.trace(bvh, ro, rd, tmax=tmax, any_hit=any_hit).triangle >= 0
                ref = (embree.occluded(ro, rd, tmax) if any_hit
                       else embree.closest(ro, rd)[1] >= 0)
                row["hit/miss differences vs Embree"] = int((ours != ref).sum())
            out.append(row)
    return out


def wide_rows(name: str, scene, repeat: int, width: int, height: int) -> dict:
    """The wide BVH, side by side and interleaved: build (SAH, leaf 8) of each width, the
    collapse included, and MRays/s of each width on all cores against embreex on one
    thread, for primary rays and AO any-hit rays (AO_PER_HIT per hit, tmax 0.1 x the
    diagonal)."""
    v, f = scene.vertices, scene.indices
    cam = type(scene.camera).from_dict({**scene.camera.to_dict(), "width": width,
                                        "height": height})
    o, d, _, _ = cam.rays()
    bvhs = {w: kernels.build_bvh(v, f, width=w) for w in WIDE_WIDTHS}
    build_s = peers.timeit_each([lambda w=w: kernels.build_bvh(v, f, width=w)
                                 for w in WIDE_WIDTHS], repeat)
    row = {"scene": name, "tris": len(f), "build_ms": {w: 1e3 * t for w, t in
                                                      zip(WIDE_WIDTHS, build_s, strict=True)},
           "collapse_ms": {w: bvhs[w].stats.phase_ms["collapse"] for w in WIDE_WIDTHS},
           "wide_nodes": {w: bvhs[w].stats.wide_nodes for w in WIDE_WIDTHS},
           "wide_stack": {w: bvhs[w].stats.wide_stack for w in WIDE_WIDTHS}}
    hits = kernels.trace(bvhs[2], o, d)
    dist = default_distance(bvhs[2])
    ao_o, ao_d = peers.ao_rays(v, f, o, d, hits.t, hits.triangle, per_hit=AO_PER_HIT)
    embree = peers.Embree(v, f)
    cores = cpu_cores()
    for kind, (ro, rd, tmax, any_hit) in {"primary": (o, d, 1e30, False),
                                          "AO": (ao_o, ao_d, dist, True)}.items():
        fns = [lambda b=bvhs[w], ro=ro, rd=rd, tmax=tmax, a=any_hit:
               kernels.trace(b, ro, rd, tmax=tmax, any_hit=a, threads=cores)
               for w in WIDE_WIDTHS]
        fns.append((lambda ro=ro, rd=rd, tmax=tmax: embree.occluded(ro, rd, tmax)) if any_hit
                   else (lambda ro=ro, rd=rd: embree.closest(ro, rd)))
        times = peers.timeit_each(fns, repeat)
        ref = (embree.occluded(ro, rd, tmax) if any_hit else embree.closest(ro, rd)[1] >= 0)
        row[kind] = {"count": len(ro), "embree_1t": len(ro) / times[-1] / 1e6}
        for w, t in zip(WIDE_WIDTHS, times, strict=False):
            ours = kernels.trace(bvhs[w], ro, rd, tmax=tmax, any_hit=any_hit).triangle >= 0
            row[kind][w] = {"mrays": len(ro) / t / 1e6, "vs_embree": times[-1] / t,
                            "embree_diff": int((ours != ref).sum())}
    return row


def wide_markdown(rows: list[dict], command: str, load: str) -> str:
    cores = cpu_cores()
    out = [
        f"Command: `{command}` on {platform.machine()} with {cores} cores, CPU only (Warp "
        f"{wp.config.version}), load before the run: {load}. Each figure is the median of "
        "interleaved runs (every width and Embree in turn, in alternating order). Ours on all "
        f"{cores} cores (host threads) against embreex (Embree 4) on ONE thread; width 2 is "
        "the binary tree, 4 and 8 the wide trees with the SIMD node test.",
        "", "### Floors", "",
        "Trace: ours / Embree 1t on primary rays and on AO any-hit rays "
        f"({AO_PER_HIT} per hit, tmax 0.1 x diagonal), floor 1.0, goal 1.5. Build: SAH leaf 8 "
        "with the collapse, over the binary build without it, floor 1.15.", "",
        "| scene | width | primary / Embree | AO / Embree | build / binary build | "
        "hit/miss diff vs Embree (primary, AO) | floors |",
        "|---|---:|---:|---:|---:|---|---|"]
    for r in rows:
        for w in WIDE_WIDTHS:
            build = r["build_ms"][w] / r["build_ms"][2]
            p, a = r["primary"][w], r["AO"][w]
            ok = p["vs_embree"] >= 1.0 and a["vs_embree"] >= 1.0 and build <= 1.15
            out.append(f"| {r['scene']} | {w} | {p['vs_embree']:.2f} | {a['vs_embree']:.2f} | "
                       f"{build:.2f} | {p['embree_diff']}, {a['embree_diff']} | "
                       f"{'PASS' if ok else 'FAIL'} |")
    out += ["", "### Figures", "",
            "| scene | tris | rays | count | Embree 1t MRays/s | "
            + " | ".join(f"width {w} MRays/s" for w in WIDE_WIDTHS) + " |",
            "|---|---:|---|---:|---:|" + "---:|" * len(WIDE_WIDTHS)]
    for r in rows:
        for kind in ("primary", "AO"):
            k = r[kind]
            out.append(f"| {r['scene']} | {r['tris']:,} | {kind} | {k['count']:,} | "
                       f"{k['embree_1t']:.2f} | "
                       + " | ".join(f"{k[w]['mrays']:.2f}" for w in WIDE_WIDTHS) + " |")
    out += ["", "| scene | " + " | ".join(f"build ms w{w}" for w in WIDE_WIDTHS)
            + " | collapse ms (w4, w8) | wide nodes (w4, w8) | stack need (w4, w8) |",
            "|---|" + "---:|" * len(WIDE_WIDTHS) + "---|---|---|"]
    for r in rows:
        out.append(f"| {r['scene']} | " + " | ".join(f"{r['build_ms'][w]:.1f}"
                                                    for w in WIDE_WIDTHS)
                   + f" | {r['collapse_ms'][4]:.2f}, {r['collapse_ms'][8]:.2f} | "
                   f"{r['wide_nodes'][4]:,}, {r['wide_nodes'][8]:,} | "
                   f"{r['wide_stack'][4]}, {r['wide_stack'][8]} |")
    return "\n".join(out) + "\n"


def thread_rows(name: str, scene, repeat: int, batches: tuple[int, ...]) -> list[dict]:
    """Ours (the default width) against embreex on the same number of threads (one share
    of the rays per Python thread: embreex_threads), for 1 thread and every core, at each
    batch of size x size camera rays and its AO any-hit rays (AO_PER_HIT per hit, tmax 0.1 x
    diagonal); timed interleaved, ours and Embree in turn."""
    v, f = scene.vertices, scene.indices
    cores = cpu_cores()
    counts = sorted({1, cores})
    bvh = kernels.build_bvh(v, f)
    embree = ThreadedEmbree(v, f, cores)
    dist = default_distance(bvh)
    rows = []
    for size in batches:
        cam = type(scene.camera).from_dict({**scene.camera.to_dict(), "width": size,
                                            "height": size})
        o, d, _, _ = cam.rays()
        hits = kernels.trace(bvh, o, d)
        ao_o, ao_d = peers.ao_rays(v, f, o, d, hits.t, hits.triangle, per_hit=AO_PER_HIT)
        for kind, (ro, rd, tmax, any_hit) in {"primary": (o, d, 1e30, False),
                                              "AO": (ao_o, ao_d, dist, True)}.items():
            def theirs(t, ro=ro, rd=rd, tmax=tmax, any_hit=any_hit):
                if any_hit:
                    return embree.occluded(ro, rd, tmax, t)
                return embree.closest(ro, rd, t) >= 0

            row = {"scene": name, "batch": size, "rays": kind, "count": len(ro)}
            for t in counts:
                ours_s, theirs_s = peers.timeit_each([
                    lambda t=t, ro=ro, rd=rd, tmax=tmax, a=any_hit:
                        kernels.trace(bvh, ro, rd, tmax=tmax, any_hit=a, threads=t),
                    lambda t=t, theirs=theirs: theirs(t)], repeat)
                row[t] = {"ours": len(ro) / ours_s / 1e6, "embree": len(ro) / theirs_s / 1e6}
            ours = kernels.trace(bvh, ro, rd, tmax=tmax, any_hit=any_hit).triangle >= 0
            row["embree_diff"] = int((ours != theirs(cores)).sum())
            rows.append(row)
    return rows


def call_rows(name: str, scene, repeat: int, calls: tuple[int, ...]) -> list[dict]:
    """Per-ray speed of calls of k rays against one call of CALL_RAYS, on the same rays (the
    first CALL_RAYS camera rays of a 1024² image, and as many of their AO any-hit rays), on
    1 thread and every core; embreex beside it, its rays split between Python threads the
    same way. Timed interleaved: the whole set as CALL_RAYS / k calls, then as one."""
    v, f = scene.vertices, scene.indices
    cores = cpu_cores()
    bvh = kernels.build_bvh(v, f)
    embree = ThreadedEmbree(v, f, cores)
    dist = default_distance(bvh)
    cam = type(scene.camera).from_dict({**scene.camera.to_dict(), "width": 1024,
                                        "height": 1024})
    o, d, _, _ = cam.rays()
    hits = kernels.trace(bvh, o, d)
    ao_o, ao_d = peers.ao_rays(v, f, o, d, hits.t, hits.triangle, per_hit=AO_PER_HIT)
    rows = []
    for kind, (ro, rd, tmax, any_hit) in {
            "primary": (o, d, 1e30, False),
            "AO": (ao_o[:CALL_RAYS], ao_d[:CALL_RAYS], dist, True)}.items():
        n = len(ro)
        ours = functools.partial(_ours_slice, bvh, ro, rd, tmax, any_hit)
        theirs = functools.partial(_embree_slice, embree, ro, rd, tmax, any_hit)
        for t in sorted({1, cores}):
            for k in calls:
                s = peers.timeit_each([functools.partial(_in_calls, fn, n, size, t)
                                       for fn in (ours, theirs) for size in (k, n)], repeat)
                rows.append({"scene": name, "rays": kind, "count": n, "threads": t,
                             "call": k, "ours": n / s[0] / 1e6, "ours_whole": n / s[1] / 1e6,
                             "embree": n / s[2] / 1e6, "embree_whole": n / s[3] / 1e6})
    return rows


def packet_rows(name: str, scene, repeat: int) -> list[dict]:
    """Closest-hit camera rays as packets against ray by ray (`trace(..., packets=False)`),
    on the same rays, 1 thread and every core, interleaved: a 512² image's rays in rows and
    in 8x8 tiles, and a 160x120 image's pixels as 8x8 rays each (as the film's samples of a
    pixel go); the rays whose t differs, and whose triangle does (at equal t)."""
    bvh = kernels.build_bvh(scene.vertices, scene.indices)
    cores = cpu_cores()
    layouts = {}
    for label, (w, h, k) in {"512² rows": (512, 512, 0), "512² 8x8 tiles": (512, 512, 8),
                             "160x120, 64 a pixel": (1280, 960, 8)}.items():
        cam = type(scene.camera).from_dict({**scene.camera.to_dict(), "width": w,
                                            "height": h})
        o, d, _, _ = cam.rays()
        if k:
            idx = np.arange(w * h).reshape(h // k, k, w // k, k).transpose(0, 2, 1, 3).ravel()
            o, d = o[idx], d[idx]
        layouts[label] = (o, d)
    rows = []
    for label, (o, d) in layouts.items():
        a, b = (kernels.trace(bvh, o, d, packets=p) for p in (False, True))
        row = {"scene": name, "rays": label, "count": len(o),
               "t_diff": int((a.t != b.t).sum()), "tri_diff": int((a.triangle != b.triangle).sum())}
        for t in sorted({1, cores}):
            single_s, packet_s = peers.timeit_each([
                lambda t=t, o=o, d=d, p=p: kernels.trace(bvh, o, d, threads=t, packets=p)
                for p in (False, True)], repeat)
            row[t] = {"single": len(o) / single_s / 1e6, "packets": len(o) / packet_s / 1e6}
        rows.append(row)
    return rows


def packets_markdown(rows: list[dict], command: str, load: str) -> str:
    counts = [k for k in rows[0] if isinstance(k, int)]
    out = [
        f"{machine_line(command, load)} Closest-hit camera rays through "
        "the default tree (SAH, leaf 8, width 8), traced ray by ray (`packets=False`) and as "
        "packets of 64 consecutive rays (kernels/bvh/packet.py), interleaved, MRays/s "
        "(medians); the rays whose t differs between the two, and whose triangle differs "
        "(at equal t, as between the tree widths: overlapping coplanar triangles).", "",
        "| scene | rays | count | " + " | ".join(
            f"ray by ray {t}t | packets {t}t | ratio {t}t" for t in counts) + " | t diff | "
        "triangle diff |",
        "|---|---|---:|" + "---:|---:|---:|" * len(counts) + "---:|---:|"]
    for r in rows:
        cells = " | ".join(f"{r[t]['single']:.2f} | {r[t]['packets']:.2f} | "
                           f"{r[t]['packets'] / r[t]['single']:.2f}" for t in counts)
        out.append(f"| {r['scene']} | {r['rays']} | {r['count']:,} | {cells} | "
                   f"{r['t_diff']} | {r['tri_diff']} |")
    return "\n".join(out) + "\n"


def _in_calls(fn, n: int, k: int, threads: int) -> None:
    """fn(a, b, threads) over [0, n) in calls of k."""
    for a in range(0, n, k):
        fn(a, min(a + k, n), threads)


def _ours_slice(bvh, o, d, tmax, any_hit, a: int, b: int, threads: int) -> None:
    kernels.trace(bvh, o[a:b], d[a:b], tmax=tmax, any_hit=any_hit, threads=threads)


def _embree_slice(embree, o, d, tmax, any_hit, a: int, b: int, threads: int) -> None:
    if any_hit:
        embree.occluded(o[a:b], d[a:b], tmax, threads)
    else:
        embree.closest(o[a:b], d[a:b], threads)


def machine_line(command: str, load: str) -> str:
    """The start of a table's header: the command, the machine, Warp, the load."""
    return (f"Command: `{command}` on {platform.machine()} with {cpu_cores()} cores, CPU only "
            f"(Warp {wp.config.version}), load before the run: {load}.")


def calls_markdown(rows: list[dict], command: str, load: str) -> str:
    out = [
        f"{machine_line(command, load)} The same rays traced as calls of "
        f"k rays and as one call of all of them ({CALL_RAYS:,} camera rays of a 1024² image; "
        f"as many AO any-hit rays, {AO_PER_HIT} per hit, tmax 0.1 x diagonal); MRays/s, "
        "medians of interleaved runs; embreex on as many Python threads beside it. Issue 35's "
        "floor: a 10k-ray call at >= 0.8x the per-ray speed of a 1M-ray call.", "",
        "| scene | rays | threads | rays per call | ours | ours, one call | ours ratio | "
        "Embree | Embree, one call | Embree ratio |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        out.append(f"| {r['scene']} | {r['rays']} | {r['threads']} | {r['call']:,} | "
                   f"{r['ours']:.2f} | {r['ours_whole']:.2f} | "
                   f"{r['ours'] / r['ours_whole']:.2f} | {r['embree']:.2f} | "
                   f"{r['embree_whole']:.2f} | {r['embree'] / r['embree_whole']:.2f} |")
    return "\n".join(out) + "\n"


def threads_markdown(rows: list[dict], command: str, load: str) -> str:
    counts = [k for k in rows[0] if isinstance(k, int)]
    out = [
        f"{machine_line(command, load)} Ours (SAH, leaf 8, the default "
        "width) on t host threads against embreex (Embree 4) on t Python threads, each "
        "tracing one share of the rays (embreex releases the Python lock); medians of "
        "interleaved runs. Camera rays at batch x batch and AO any-hit rays "
        f"({AO_PER_HIT} per hit, tmax 0.1 x diagonal). Issue floor: ours / Embree >= 1.0 on "
        "the same threads.", "",
        "| scene | batch | rays | count | "
        + " | ".join(f"ours {t}t | Embree {t}t | ours / Embree {t}t" for t in counts)
        + " | hit/miss diff |",
        "|---|---:|---|---:|" + "---:|---:|---:|" * len(counts) + "---:|"]
    for r in rows:
        cells = " | ".join(f"{r[t]['ours']:.2f} | {r[t]['embree']:.2f} | "
                           f"{r[t]['ours'] / r[t]['embree']:.2f}" for t in counts)
        out.append(f"| {r['scene']} | {r['batch']}² | {r['rays']} | {r['count']:,} | {cells} "
                   f"| {r['embree_diff']} |")
    return "\n".join(out) + "\n"


def floors(build: list[dict], peer_build: dict, traces: list[dict]) -> list[str]:
    """The BVH floors, per scene: SAH build (ours, leaf_size 8, all cores) <= 1.5x
    `wp.Mesh(bvh_constructor="sah")` as users call it (its default leaf size 4) at equal or
    lower SAH cost; closest and any hit >= 1.0x wp.Mesh on one thread and >= 1.8x with all
    cores."""
    cores = cpu_cores()
    out = ["### Floors", "",
           "SAH build: ours (leaf_size 8, a maximum: SAH makes smaller leaves where cheaper) on "
           "all cores against `wp.Mesh(bvh_constructor=\"sah\")` at its defaults, at equal or "
           "lower SAH cost (floor 1.5x). Trace: ours / wp.Mesh MRays/s on the same rays, one "
           f"thread (floor 1.0) and {cores} cores against wp.Mesh on one thread (floor 1.8).",
           "", "| scene | build ours / wp.Mesh | SAH cost ours, wp.Mesh | trace 1t (min over "
           "ray kinds) | trace all cores / wp.Mesh 1t (min) | floors |",
           "|---|---:|---:|---:|---:|---|"]
    met = 0
    for scene, pb in peer_build.items():
        r = next(r for r in build if r["scene"] == scene and r["method"] == "sah"
                 and r["leaf"] == 8)
        build_ratio = r["ms_all"] / r["wp_mesh_default_ms"]  # timed in turn with ours
        theirs = pb["wp.Mesh sah cost (leaf 4)"]
        rows = [t for t in traces if t["scene"] == scene and t["bvh"] == "sah"]
        one = min(t["ours 1t"] / t["wp.Mesh 1t"] for t in rows)
        all_ = min(t[f"ours {cores}t"] / t["wp.Mesh 1t"] for t in rows)
        ok = build_ratio <= 1.5 and r["sah"] <= theirs and one >= 1.0 and all_ >= 1.8
        met += ok
        out.append(f"| {scene} | {build_ratio:.2f} | {r['sah']:.1f}, {theirs:.1f} | {one:.2f} "
                   f"| {all_:.2f} | {'PASS' if ok else 'FAIL'} |")
    return out + ["", f"All floors met on {met} of {len(peer_build)} scenes.", ""]


def markdown(build: list[dict], peer_build: dict, traces: list[dict], compile_s: dict,
             command: str) -> str:
    lines = [
        f"Command: `{command}` on {platform.machine()} with {cpu_cores()} cores, CPU only "
        f"(Warp {wp.config.version}). Medians after one warm-up; compile time is separate: "
        + ", ".join(f"{k} {v:.1f} s" for k, v in compile_s.items()) + " (first use, empty "
        "kernel cache). The 2 cores are shared with other work, so all-core figures may sit "
        "close to one-thread ones. Ratio columns: build is ours ms / wp.Mesh ms (above 1: "
        "ours slower); trace is ours MRays/s / wp.Mesh MRays/s (above 1: ours faster). "
        "Embree traces on one thread only (embreex holds the Python lock).",
        "",
        "### Build (build columns of Tables 6.1 median and 6.2 SAH): ours on all cores and on "
        "one worker, against the peers",
        "",
        "`wp.Mesh ms` is `wp.Mesh(bvh_constructor=method, bvh_leaf_size=leaf)`: the same "
        "method and leaf size as ours. Its SAH cost (leaf 8) is replayed in numpy from "
        "warp/native/bvh.cpp, since Warp does not expose its nodes.",
        "",
        "| scene | tris | method | leaf | ms (all cores) | ms (1 worker) | MTris/s | SAH cost "
        "| nodes | depth | wp.Mesh ms | ours / wp.Mesh (all, 1) |",
        "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in build:
        ref = r["wp_mesh_ms"]
        lines.append(
            f"| {r['scene']} | {r['tris']:,} | {r['method']} | {r['leaf']} | {r['ms_all']:.1f} "
            f"| {r['ms_one']:.1f} | {r['mtris_s']:.2f} | {r['sah']:.1f} | {r['nodes']:,} | "
            f"{r['depth']} | {ref:.1f} | {r['ms_all'] / ref:.2f}, {r['ms_one'] / ref:.2f} |")
    lines += ["", "Peers at their defaults (wp.Mesh leaf size 4), build ms, and wp.Mesh's SAH "
              "cost at leaf 8 against ours (sah, leaf 8):", ""]
    for s, pb in peer_build.items():
        ours = next(r["sah"] for r in build if r["scene"] == s and r["method"] == "sah"
                    and r["leaf"] == 8)
        lines.append(f"- {s}: " + ", ".join(f"{k} {v:.1f}" for k, v in pb.items()
                                            if "cost" not in k)
                     + f"; SAH cost wp.Mesh {pb['wp.Mesh sah cost (leaf 8)']:.1f}, "
                     f"ours {ours:.1f}")
    lines.append("")
    lines += floors(build, peer_build, traces)
    lines += ["### Trace (trace columns of Tables 6.1/6.2, our SAH leaf 8 against wp.Mesh sah): "
              "MRays/s", ""]
    keys = [k for k in traces[0] if k not in ("scene", "bvh", "rays", "count")]
    lines.append("| scene | bvh | rays | count | " + " | ".join(keys)
                 + " | ours / wp.Mesh (1t, all) |")
    lines.append("|---|---|---|---:|" + "---:|" * len(keys) + "---|")
    cores = cpu_cores()
    for r in traces:
        cells = [f"{r[k]:.2f}" if isinstance(r.get(k), float) else str(r.get(k, "")) for k in keys]
        ratio = (f"{r['ours 1t'] / r['wp.Mesh 1t']:.2f}, "
                 f"{r[f'ours {cores}t'] / r[f'wp.Mesh {cores}t']:.2f}")
        lines.append(f"| {r['scene']} | {r['bvh']} | {r['rays']} | {r['count']:,} | "
                     + " | ".join(cells) + f" | {ratio} |")
    return "\n".join(lines) + "\n"


# --part: (rows of one scene, markdown, docs section, its title)
TABLE_PARTS = {
    "threads": (lambda name, scene, args: thread_rows(
        name, scene, args.repeat, tuple(int(x) for x in args.batches.split(","))),
        threads_markdown, "bvh_threads", "Ours against Embree on the same threads"),
    "packets": (lambda name, scene, args: packet_rows(name, scene, args.repeat),
                packets_markdown, "bvh_packets", "Camera rays as packets against ray by ray"),
    "calls": (lambda name, scene, args: call_rows(
        name, scene, args.repeat, tuple(int(x) for x in args.calls.split(","))),
        calls_markdown, "bvh_calls", "Small calls against one large call"),
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default=",".join(shared_scene_infos()))
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--width", type=int, default=1024)
    parser.add_argument("--height", type=int, default=768)
    parser.add_argument("--part", choices=("all", "wide", "threads", "calls", "packets"),
                        default="all",
                        help="wide: only the wide-BVH tables; threads: only ours against "
                        "Embree on the same threads; calls: only small calls' speed; "
                        "packets: closest-hit camera rays as packets against ray by ray")
    parser.add_argument("--calls", default=",".join(map(str, CALLS)),
                        help="--part calls: rays per call")
    parser.add_argument("--batches", default=",".join(map(str, BATCHES)),
                        help="--part threads: square batch sizes")
    parser.add_argument("--no-docs", action="store_true", help="print only")
    parser.add_argument("--target-cpu", help="compile the engine for this clang target CPU, "
                        "not the host's (x86-64: no AVX2, the wide trees traversed lane by "
                        "lane; x86-64-v3: AVX2); needs --no-docs")
    args = parser.parse_args(argv)
    if args.target_cpu:
        if not args.no_docs:
            parser.error("--target-cpu measures another target than the documented one: "
                         "add --no-docs")
        wp.config.cpu_compiler_flags = cpu_target_flags(args.target_cpu)
    command = "python benchmarks/bvh.py " + " ".join(argv if argv is not None else sys.argv[1:])
    wp.init()
    load = "{:.2f}, {:.2f}, {:.2f} (1, 5, 15 min)".format(*os.getloadavg())
    compile_s = compile_seconds()
    if args.part in TABLE_PARTS:
        rows_of, markdown_of, section, title = TABLE_PARTS[args.part]
        rows = []
        for name in args.scenes.split(","):
            rows += rows_of(name, shared_scene(name), args)
            print(f"{name}: {args.part} done", file=sys.stderr, flush=True)
        text = markdown_of(rows, command.strip(), load)
        Console(width=220).print(Markdown(text))
        if not args.no_docs:
            write_section(section, f"## {title} (`benchmarks/bvh.py --part {args.part}`)\n\n"
                          + text)
            FIGURES.mkdir(parents=True, exist_ok=True)
            (FIGURES / f"{section}.json").write_text(json.dumps(rows, indent=1, default=str))
        return 0
    wide = []
    for name in args.scenes.split(","):
        wide.append(wide_rows(name, shared_scene(name), args.repeat, args.width, args.height))
        print(f"{name}: wide done", file=sys.stderr, flush=True)
    wide_text = wide_markdown(wide, command.strip(), load)
    Console(width=200).print(Markdown(wide_text))
    if not args.no_docs:
        write_section("bvh_wide", "## Wide BVH with SIMD node tests against Embree "
                      "(`benchmarks/bvh.py`)\n\n" + wide_text)
        FIGURES.mkdir(parents=True, exist_ok=True)
        (FIGURES / "bvh_wide.json").write_text(json.dumps(wide, indent=1, default=str))
    if args.part == "wide":
        return 0
    build, peer_build, traces = [], {}, []
    for name in args.scenes.split(","):
        scene = shared_scene(name)
        rows, peer_build[name] = build_rows(name, scene.vertices, scene.indices, args.repeat)
        for r in rows:
            r["tris"] = len(scene.indices)
        build += rows
        traces += trace_rows(name, scene, args.repeat, args.width, args.height)
        print(f"{name}: done", file=sys.stderr, flush=True)
    text = markdown(build, peer_build, traces, compile_s, command.strip())
    Console(width=200).print(Markdown(text))
    if not args.no_docs:
        write_section("bvh", "## BVH construction and traversal (`benchmarks/bvh.py`)\n\n"
                      + text)
        FIGURES.mkdir(parents=True, exist_ok=True)
        (FIGURES / "bvh.json").write_text(json.dumps(
            {"compile_s": compile_s, "build": build, "peer_build": peer_build,
             "trace": traces, "cores": cpu_cores(), "pid": os.getpid()}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
