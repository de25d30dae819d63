"""The papers' GPU tables on one CUDA device, against Warp's `wp.Mesh` on the same device and
the same rays.

    python benchmarks/gpu_tables.py [--parts trace,build,dacrt,sweep] [--scenes ...]
        [--size 1024] [--repeat 5] [--budget 300] [--json out.json] [--device cuda:0]

build: the build columns of the 2012 paper's Tables 6.1 (spatial median) and 6.2 (binned
  SAH) at leaf sizes 8, 16 and 32, on the shared scenes and on a 1.1 M-triangle scene (the
  bunny subdivided twice); beside `wp.Mesh(bvh_constructor="sah")` (built on the host) and
  "lbvh" (on the device) from device arrays. Ours: the wall time of `build_bvh` (numpy in:
  the upload counted), `build_ms` (from the upload on) and the pool's persistent launch.
trace: the trace columns of Tables 6.1/6.2: size^2 primary rays (the scene's camera), 7
  ambient-occlusion rays per primary hit (cosine-weighted, within 0.1 of the scene box's
  diagonal, any hit) and size^2 random rays (origins in the scene box, uniform directions,
  closest hit), MRays/s of the kernel alone (rays and hits on the device, CUDA events);
  ours at widths 2, 4 and 8 against `wp.Mesh` sah and lbvh. Every result is checked: ours
  on the device against ours on the CPU for every 16th ray (hit/miss and triangle
  differences, largest relative t difference), and the hit/miss differences of `wp.Mesh`.
dacrt: Table 6.3 (task-pool DACRT, spatial median and RDH, size/2 and size, primary, AO and
  random rays, MRays/s) and the 2013 paper's Tables 1-3 (breadth-first DACRT, ms per frame
  for primary, shadow, specular and AO rays at size^2, peak memory), with the papers'
  constants; each result's hit/miss differences against the BVH's.
sweep: the persistent workers and K of the build and of the task-pool DACRT, and the
  block size of the trace kernel.
Device rows are medians of --repeat runs after a warm-up, compilation excluded. Rows stop
being added once --budget seconds have passed (they are then listed as skipped).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np
import warp as wp

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO), str(REPO / "benchmarks")]
wp.config.quiet = True

from dacrt import TUNINGS, scene_rays  # noqa: E402
from scenesort.backend.render.scenes import shared_scene  # noqa: E402
from scenesort.backend.tools.peers import _mesh_closest, _mesh_occluded, ao_rays, random_rays  # noqa: E402
from scenesort.kernels.bvh.build_data import PHASE_NAMES  # noqa: E402
from scenesort.kernels.bvh.traversal import trace_kernel  # noqa: E402
from scenesort.kernels.core.claim import unclaimed  # noqa: E402

from scenesort import kernels  # noqa: E402

PAPER_SCENES = ("conference", "sponza", "sibenik", "bunny", "dragon", "buddha", "blade")
BIG = "bunny4x"  # the bunny subdivided twice: 1.1 M triangles
AO_PER_HIT = 7  # 2012 paper: 7 AO rays per primary ray
CHECK_EVERY = 16  # the CPU checks every 16th ray


class Clock:
    """The run's budget: rows start only while time is left."""

    def __init__(self, budget_s: float) -> None:
        self.end = time.perf_counter() + budget_s
        self.skipped: list[str] = []

    def ok(self, what: str) -> bool:
        if time.perf_counter() < self.end:
            return True
        self.skipped.append(what)
        return False


class Rows(list):
    """The rows so far, written to `path` (JSON, with `head`) after every one: a run that
    runs out of time keeps what it measured."""

    def __init__(self, path: str | None, head: dict, clock: Clock) -> None:
        super().__init__()
        self.path, self.head, self.clock = path, head, clock

    def append(self, row: dict) -> None:
        super().append(row)
        if self.path:
            Path(self.path).write_text(json.dumps(
                {**self.head, "rows": list(self), "skipped": self.clock.skipped}, indent=1))


def scene_of(name: str, size: int):
    from dataclasses import replace

    if name == BIG:
        import trimesh

        base = shared_scene("bunny")
        v, f = base.vertices.astype(np.float64), base.indices
        for _ in range(2):
            v, f = trimesh.remesh.subdivide(v, f)
        return replace(base, name=BIG, vertices=v.astype(np.float32),
                       indices=f.astype(np.int32),
                       camera=replace(base.camera, width=size, height=size))
    s = shared_scene(name)
    return replace(s, camera=replace(s.camera, width=size, height=size))


def device_ms(fn: Callable[[], object], device, repeat: int) -> float:
    """Median ms of `repeat` calls after one warm-up: CUDA events on a GPU, else wall."""
    fn()
    samples = []
    for _ in range(repeat):
        if device.is_cuda:
            stream = wp.get_stream(device)
            e0, e1 = (wp.Event(device, enable_timing=True) for _ in range(2))
            stream.record_event(e0)
            fn()
            stream.record_event(e1)
            samples.append(wp.get_event_elapsed_time(e0, e1))
        else:
            t0 = time.perf_counter()
            fn()
            wp.synchronize_device(device)
            samples.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(samples)


def wall_ms(fn: Callable[[], object], device, repeat: int) -> tuple[float, object]:
    out = fn()
    samples = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        wp.synchronize_device(device)
        samples.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(samples), out


def warp_mesh(v: np.ndarray, f: np.ndarray, constructor: str, device) -> tuple[wp.Mesh, list]:
    pts = wp.array(v, dtype=wp.vec3, device=device)
    idx = wp.array(np.ascontiguousarray(f).ravel(), dtype=int, device=device)
    return wp.Mesh(points=pts, indices=idx, bvh_constructor=constructor), [pts, idx]


def mesh_constructors(device) -> tuple[str, ...]:
    return ("sah", "lbvh") if device.is_cuda else ("sah",)


# ---------------------------------------------------------------- build


def part_build(args, device, clock: Clock, rows: list[dict]) -> None:
    for name in args.scenes + [BIG]:
        if not clock.ok(f"build {name}"):
            continue
        s = scene_of(name, args.size)
        v, f = s.vertices, s.indices
        for method in ("median", "sah"):
            for leaf in (8, 16, 32):
                if not clock.ok(f"build {name} {method} {leaf}"):
                    continue
                ms, bvh = wall_ms(partial(kernels.build_bvh, v, f, method=method,
                                          leaf_size=leaf, device=device), device, args.repeat)
                st = bvh.stats
                rows.append({"part": "build", "scene": name, "tris": len(f), "who": "ours",
                             "method": method, "leaf": leaf, "wall_ms": ms,
                             "build_ms": st.build_ms,
                             "pool_ms": sum(st.phase_ms.get(p, 0.0) for p in PHASE_NAMES),
                             "phase_ms": st.phase_ms, "sah_cost": st.sah_cost,
                             "nodes": st.nodes, "depth": st.depth,
                             "workers": st.workers})
        for ctor in mesh_constructors(device):
            if not clock.ok(f"build {name} wp.Mesh {ctor}"):
                continue
            ms, _ = wall_ms(partial(warp_mesh, v, f, ctor, device), device, args.repeat)
            rows.append({"part": "build", "scene": name, "tris": len(f),
                         "who": f"wp.Mesh {ctor}", "method": ctor, "leaf": None, "wall_ms": ms})


# ---------------------------------------------------------------- trace


def ray_sets(s, bvh_cpu) -> dict[str, tuple[np.ndarray, ...]]:
    """primary, ao and random rays: (origins, directions, tmin, tmax, any_hit)."""
    o, d, tmin, tmax = s.camera.rays()
    ref = kernels.trace(bvh_cpu, o, d, tmin, tmax)
    diag = float(np.linalg.norm(bvh_cpu.bounds[1] - bvh_cpu.bounds[0]))
    ao_o, ao_d = ao_rays(s.vertices, s.indices, o, d, ref.t, ref.triangle, AO_PER_HIT)
    ro, rd = random_rays(bvh_cpu.bounds, len(o))
    one = np.zeros(1, np.float32)
    return {
        "primary": (o, d, tmin, tmax, 0),
        "ao": (ao_o, ao_d, one, np.full(1, 0.1 * diag, np.float32), 1),
        "random": (ro, rd, one, np.full(1, np.inf, np.float32), 0),
    }


def hitmiss(hits, ref) -> int:
    return int(np.count_nonzero((hits.triangle >= 0) != (ref.triangle >= 0)))


def compare(t_dev, tri_dev, ref, any_hit: int) -> dict:
    """Ours on the device against ours on the CPU, on the checked rays (any hit: hit or
    miss only, the triangle found first may differ)."""
    hit_d, hit_c = tri_dev >= 0, ref.triangle >= 0
    if any_hit:
        return {"hitmiss": int(np.count_nonzero(hit_d != hit_c))}
    both = hit_d & hit_c
    rel = np.abs(t_dev[both] - ref.t[both]) / np.maximum(np.abs(ref.t[both]), 1e-30)
    return {"hitmiss": int(np.count_nonzero(hit_d != hit_c)),
            "tri_diff": int(np.count_nonzero(tri_dev[both] != ref.triangle[both])),
            "max_rel_t": float(rel.max()) if len(rel) else 0.0}


def part_trace(args, device, clock: Clock, rows: list[dict]) -> None:
    for name in args.scenes:
        if not clock.ok(f"trace {name}"):
            continue
        s = scene_of(name, args.size)
        v, f = s.vertices, s.indices
        bvh_cpu = kernels.build_bvh(v, f, width=2, device="cpu")
        sets = ray_sets(s, bvh_cpu)
        dev_sets = {}
        for kind, (o, d, tmin, tmax, any_hit) in sets.items():
            ref = kernels.trace(bvh_cpu, o[::CHECK_EVERY], d[::CHECK_EVERY],
                                tmin[::CHECK_EVERY] if len(tmin) > 1 else tmin[0],
                                tmax[::CHECK_EVERY] if len(tmax) > 1 else tmax[0],
                                any_hit=bool(any_hit))
            dev_sets[kind] = ([wp.array(x, dtype=dt, device=device) for x, dt in
                               ((o, wp.vec3), (d, wp.vec3), (tmin, float), (tmax, float))],
                              any_hit, ref)
        ours_hits = {}
        for width in args.widths:
            if not clock.ok(f"trace {name} width {width}"):
                continue
            bvh = kernels.build_bvh(v, f, width=width, device=device)
            for kind, (arrs, any_hit, ref) in dev_sets.items():
                n = arrs[0].shape[0]
                out = [wp.empty(n, dtype=dt, device=device) for dt in (float, int, float, float)]

                invalid = wp.zeros(1, dtype=int, device=device)
                ms = device_ms(partial(wp.launch, trace_kernel, dim=n,
                                       inputs=[bvh.arrays, *arrs, any_hit, *out, invalid,
                                               unclaimed(n, 1, device)], device=device),
                               device, args.repeat)
                t, tri = out[0].numpy(), out[1].numpy()
                ours_hits[(width, kind)] = tri >= 0
                rows.append({"part": "trace", "scene": name, "tris": len(f), "kind": kind,
                             "who": f"ours w{width}", "rays": n, "ms": ms,
                             "mrays_s": n / ms / 1e3,
                             **compare(t[::CHECK_EVERY], tri[::CHECK_EVERY], ref, any_hit)})
        for ctor in mesh_constructors(device):
            if not clock.ok(f"trace {name} wp.Mesh {ctor}"):
                continue
            mesh, keep = warp_mesh(v, f, ctor, device)
            for kind, (arrs, any_hit, _ref) in dev_sets.items():
                n = arrs[0].shape[0]
                tmax = float(sets[kind][3].max()) if kind != "primary" else 1e30
                tmax = 1e30 if not np.isfinite(tmax) else tmax
                if any_hit:
                    out = [wp.empty(n, dtype=int, device=device)]
                    kern = _mesh_occluded
                else:
                    out = [wp.empty(n, dtype=float, device=device),
                           wp.empty(n, dtype=int, device=device)]
                    kern = _mesh_closest

                ms = device_ms(partial(wp.launch, kern, dim=n,
                                       inputs=[mesh.id, arrs[0], arrs[1], tmax, *out,
                                               unclaimed(n, 1, device)], device=device),
                               device, args.repeat)
                hit = out[-1].numpy() > 0 if any_hit else out[1].numpy() >= 0
                ours = ours_hits.get((2, kind))
                rows.append({"part": "trace", "scene": name, "tris": len(f), "kind": kind,
                             "who": f"wp.Mesh {ctor}", "rays": n, "ms": ms,
                             "mrays_s": n / ms / 1e3,
                             "vs_ours_hitmiss": None if ours is None else
                             int(np.count_nonzero(hit != ours))})


# ---------------------------------------------------------------- dacrt


def part_dacrt(args, device, clock: Clock, rows: list[dict]) -> None:
    rng = np.random.default_rng(0)
    for name in args.dacrt_scenes:
        s = scene_of(name, args.size)
        v, f = s.vertices, s.indices
        bvh = kernels.build_bvh(v, f, device=device)
        # cheapest first: the budget cuts the tail
        for size, kinds, methods in ((args.size, ("primary", "shadow", "specular", "ao"),
                                      ("bf",)),
                                     (args.size // 2, ("primary", "random", "ao"),
                                      ("median", "rdh")),
                                     (args.size, ("primary", "random", "ao"), ("median", "rdh"))):
            sized = scene_of(name, size)
            primary = kernels.trace(bvh, *sized.camera.rays())
            for kind in kinds:
                o, d, tmin, tmax = scene_rays(sized, size, kind, primary, rng)
                ref = kernels.trace(bvh, o, d, tmin, tmax)
                for method in methods:
                    if not clock.ok(f"dacrt {name} {size} {kind} {method}"):
                        continue
                    variant, split = ("breadth_first", "rdh") if method == "bf" else \
                        ("pool", method)
                    stats = kernels.DacrtStats()
                    ms, hits = wall_ms(partial(kernels.dacrt_trace, v, f, o, d, tmin, tmax,
                                               variant=variant, split=split, device=device,
                                               stats=stats, **TUNINGS["paper"][variant]),
                                       device, max(1, args.repeat // 2))
                    rows.append({"part": "dacrt", "scene": name, "tris": len(f), "size": size,
                                 "kind": kind, "method": method, "rays": len(o),
                                 "wall_ms": ms, "trace_ms": stats.trace_ms,
                                 "mrays_s": len(o) / stats.trace_ms / 1e3,
                                 "peak_mb": stats.peak_bytes / 2**20,
                                 "hitmiss_vs_bvh": hitmiss(hits, ref),
                                 "stats": {k: x for k, x in stats.items()
                                           if isinstance(x, int | float | str | dict)}})


# ---------------------------------------------------------------- sweep


def part_sweep(args, device, clock: Clock, rows: list[dict]) -> None:
    """The persistent workers and K of the build, the workers and C_SORT of the task-pool
    DACRT, alpha and beta of the breadth-first DACRT, the trace kernel's block size."""
    sms = device.sm_count if device.is_cuda else 1
    name = args.scenes[0]
    for scene_name in (name, BIG):
        s = scene_of(scene_name, args.size)
        for workers in sorted({sms * k for k in (4, 16, 64, 256)}):
            for k in (4, 14, 64):
                if not clock.ok(f"sweep build {scene_name} {workers} {k}"):
                    continue
                ms, bvh = wall_ms(partial(kernels.build_bvh, s.vertices, s.indices,
                                          device=device, workers=workers, min_chunks=k),
                                  device, max(1, args.repeat // 2))
                rows.append({"part": "sweep", "what": "build sah 8", "scene": scene_name,
                             "workers": workers, "k": k, "wall_ms": ms,
                             "build_ms": bvh.stats.build_ms, "nodes": bvh.stats.nodes,
                             "sah_cost": bvh.stats.sah_cost,
                             "pool_ms": sum(bvh.stats.phase_ms.get(p, 0.0)
                                            for p in PHASE_NAMES)})
    small = scene_of(args.dacrt_scenes[1], args.size // 2)
    o, d, tmin, tmax = small.camera.rays()
    ref = kernels.trace(kernels.build_bvh(small.vertices, small.indices, device=device), o, d,
                        tmin, tmax)
    for c_sort in (4.0, 80.0):
        for workers in sorted({sms * k for k in (8, 32, 128, 256)}):
            if not clock.ok(f"sweep dacrt {workers} {c_sort}"):
                continue
            stats = kernels.DacrtStats()
            ms, hits = wall_ms(partial(kernels.dacrt_trace, small.vertices, small.indices, o, d,
                                    tmin, tmax, device=device, workers=workers, c_sort=c_sort,
                                    min_rays=16 if c_sort < 80 else 32, stats=stats),
                            device, 1)
            rows.append({"part": "sweep", "what": f"dacrt pool rdh c_sort {c_sort:g}",
                         "scene": f"{small.name} {args.size // 2}", "workers": workers,
                         "wall_ms": ms, "trace_ms": stats.trace_ms,
                         "hitmiss_vs_bvh": hitmiss(hits, ref),
                         "stats": {k: x for k, x in stats.items()
                                   if isinstance(x, int | float | str | dict)}})
    s = scene_of(args.dacrt_scenes[0], args.size)
    o, d, tmin, tmax = s.camera.rays()
    ref = kernels.trace(kernels.build_bvh(s.vertices, s.indices, device=device), o, d, tmin,
                        tmax)
    for alpha, beta in ((32, 128), (256, 256), (64, 1024), (1024, 1024), (4096, 4096)):
        if not clock.ok(f"sweep bf {alpha} {beta}"):
            continue
        stats = kernels.DacrtStats()
        ms, hits = wall_ms(partial(kernels.dacrt_trace, s.vertices, s.indices, o, d, tmin, tmax,
                                variant="breadth_first", device=device, alpha=alpha, beta=beta,
                                stats=stats), device, args.repeat)
        rows.append({"part": "sweep", "what": f"dacrt bf alpha {alpha} beta {beta}",
                     "scene": f"{s.name} {args.size}", "wall_ms": ms,
                     "trace_ms": stats.trace_ms, "hitmiss_vs_bvh": hitmiss(hits, ref),
                     "stats": {k: x for k, x in stats.items()
                               if isinstance(x, int | float | str | dict)}})
    name = s.name
    bvh = kernels.build_bvh(s.vertices, s.indices, width=2, device=device)
    arrs = [wp.array(x, dtype=dt, device=device)
            for x, dt in ((o, wp.vec3), (d, wp.vec3), (tmin, float), (tmax, float))]
    out = [wp.empty(len(o), dtype=dt, device=device) for dt in (float, int, float, float)]
    invalid = wp.zeros(1, dtype=int, device=device)
    for block in (32, 64, 128, 256, 512):
        if not clock.ok(f"sweep trace block {block}"):
            continue
        ms = device_ms(partial(wp.launch, trace_kernel, dim=len(o),
                               inputs=[bvh.arrays, *arrs, 0, *out, invalid,
                                       unclaimed(len(o), 1, device)],
                               device=device, block_dim=block), device, args.repeat)
        rows.append({"part": "sweep", "what": "trace primary w2 block_dim", "scene": name,
                     "block_dim": block, "ms": ms, "mrays_s": len(o) / ms / 1e3})


# ---------------------------------------------------------------- tables


def table(rows: list[dict], cols: list[str]) -> str:
    def fmt(x) -> str:
        if isinstance(x, float):
            return f"{x:.3g}" if abs(x) < 100 else f"{x:,.0f}"
        return "" if x is None else str(x)

    body = [[fmt(r.get(c)) for c in cols] for r in rows]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(b) + " |" for b in body]
    return "\n".join(lines)


def print_tables(rows: list[dict]) -> None:
    for part, cols in (
        ("build", ["scene", "tris", "who", "method", "leaf", "wall_ms", "build_ms", "pool_ms",
                   "sah_cost", "workers"]),
        ("trace", ["scene", "kind", "who", "rays", "ms", "mrays_s", "hitmiss", "tri_diff",
                   "max_rel_t", "vs_ours_hitmiss"]),
        ("dacrt", ["scene", "size", "kind", "method", "rays", "wall_ms", "trace_ms", "mrays_s",
                   "peak_mb", "hitmiss_vs_bvh"]),
        ("sweep", ["what", "scene", "workers", "k", "block_dim", "wall_ms", "build_ms",
                   "pool_ms", "nodes", "trace_ms", "ms", "mrays_s", "hitmiss_vs_bvh"]),
    ):
        sel = [r for r in rows if r["part"] == part]
        if sel:
            print(f"\n## {part}\n")
            print(table(sel, cols))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--parts", default="trace,sweep,dacrt,build")
    p.add_argument("--widths", default=None,
                   help="BVH widths traced (default: 2 on CUDA, whose kernels traverse the "
                        "binary tree whatever the width; 2,4,8 on CPU)")
    p.add_argument("--scenes", default="conference,sponza,sibenik,bunny,dragon,buddha,blade")
    p.add_argument("--dacrt-scenes", default="conference,sponza,bunny")
    p.add_argument("--size", type=int, default=1024)
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--budget", type=float, default=300.0)
    p.add_argument("--device", default="cuda:0")
    p.add_argument("--json", default=None)
    args = p.parse_args()
    args.scenes = args.scenes.split(",")
    args.dacrt_scenes = args.dacrt_scenes.split(",")
    wp.init()
    device = wp.get_device(args.device)
    args.widths = [int(w) for w in (args.widths or ("2" if device.is_cuda else "2,4,8"))
                   .split(",")]
    print(f"device {device}: {device.name}; size {args.size}; repeat {args.repeat}", flush=True)
    clock = Clock(args.budget)
    runtime = wp._src.context.runtime
    meta = {"warp": wp.config.version, "size": args.size, "repeat": args.repeat,
            "date": time.strftime("%Y-%m-%d"), "sms": getattr(device, "sm_count", None),
            "driver": ".".join(map(str, runtime.driver_version or ())),
            "toolkit": ".".join(map(str, runtime.toolkit_version or ())),
            "argv": sys.argv[1:]}
    rows = Rows(args.json, {"device": device.name, "meta": meta}, clock)
    parts = {"build": part_build, "trace": part_trace, "dacrt": part_dacrt,
             "sweep": part_sweep}
    for part in args.parts.split(","):
        t0 = time.perf_counter()
        try:
            parts[part](args, device, clock, rows)
        except Exception as exc:  # one part's failure must not lose the others' rows
            import traceback

            traceback.print_exc()
            rows.append({"part": part, "error": f"{type(exc).__name__}: {exc}"})
        print(f"[{part}: {time.perf_counter() - t0:.1f} s, {len(rows)} rows]", flush=True)
    print_tables(rows)
    errors = [r for r in rows if "error" in r]
    for r in errors:
        print(f"ERROR in {r['part']}: {r['error']}")
    if clock.skipped:
        print(f"skipped (budget): {len(clock.skipped)} rows, first: {clock.skipped[0]}")
    return 1 if errors else 0


if __name__ == "__main__":
    raise SystemExit(main())
