"""Run time against error for ambient occlusion: our renderer (fixed spp with Sobol and
random samples, adaptive `target_error` and the per-pixel `max_pixel_error`) against
fixed-spp AO traced by Warp's own `wp.Mesh` (`mesh_query_ray_anyhit`) and by Embree with
exactly our occlusion directions.

    .venv/bin/python benchmarks/ao_error.py                       # every scene, 512 wide
    .venv/bin/python benchmarks/ao_error.py --scenes bunny,sponza --width 256
    .venv/bin/python benchmarks/ao_error.py --quick --width 128   # fewer points, 1024-spp ref

Error is the RMSE over the pixels whose primary ray hits, against a reference of
`--ref-spp` independent samples per pixel traced by Embree (cached under .cache/ao_ref),
with the reference's own variance removed (its samples are independent Bernoulli trials,
so MSE(est) = MSE(est, ref) - Var(ref)). Times are wall clock, median of `--repeat`,
from camera rays to AO: ours = `render_ao` (primary + occlusion); peers = their own
primary closest-hit launch + their occlusion launch (ray generation not counted for them).
"wp.Mesh" gets as many host threads as ours (its launches split the way ours are: the
floor is judged against this, the stronger peer); "wp.Mesh 1t" is one launch, as Warp runs
it on CPU; embreex holds the GIL, so Embree runs on one thread.

Floors (the AO error floors), on every scene, at target_error 0.05, 0.02 and 0.01:
- calibration: the achieved RMSE lies in [0.7, 1.0] x target_error;
- cost: the render takes <= 1.15x the time of the cheapest fixed spp (Sobol, same tracer,
  chosen in hindsight from the fixed sweep, a grid of ~1.5x steps: the fewest spp whose RMSE
  is at most the one achieved; timed again in alternation with the render), and >= 2x less
  than `max_pixel_error` (the per-pixel rule) given the same number
  (measured at 0.05 and 0.02, in the same alternation: at 0.01 that rule needs thousands of
  samples a pixel).
With --denoise, every point of ours is also denoised (`render_ao(denoise=True)`, OIDN with
the normal image): "ours sobol denoised" and "ours target_error denoised" are the same
renders' denoised images, their RMSE against the same reference and their time including
the denoise (the raw points' time is the same run's total less the denoise).
Writes docs/figures/ao_error.png and the AO section of docs/benchmarks.md unless --no-docs.
"""

from __future__ import annotations

import argparse
import copy
import hashlib
import math
import os
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import warp as wp

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from docs_section import write_section  # noqa: E402  (benchmarks/ is on sys.path)
from scenesort.backend.render.scenes import shared_scene, shared_scene_infos  # noqa: E402
from scenesort.backend.tools import peers  # noqa: E402
from scenesort.kernels.core import host_threads  # noqa: E402
from scenesort.kernels.render import ao, primary, surface, tracers  # noqa: E402

from scenesort import ao_options as options  # noqa: E402
from scenesort import kernels  # noqa: E402

RMSE_GOAL = 0.02
FIXED_SPP = (1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64, 96, 128, 192, 256, 384)
PEER_SPP = (1, 2, 4, 8, 16, 32, 64, 128, 256)  # peers: powers of two only
FLOOR_TARGETS = (0.05, 0.02, 0.01)
TARGETS = (0.1, 0.07, 0.05, 0.035, 0.02, 0.014, 0.01, 0.007)
OLD_RULE_TARGETS = (0.05, 0.02)  # max_pixel_error at the same number
QUICK_TARGETS = FLOOR_TARGETS
CALIBRATION = (0.7, 1.0)
COST_FLOOR = 1.15  # time to a target over the cheapest fixed spp reaching its RMSE
OLD_RULE_FLOOR = 2.0  # max_pixel_error's time over target_error's, same number
PEER_CHUNK = 1 << 21  # occlusion rays per peer launch (bounds memory)
ADAPTIVE_NOTE = (
    'Adaptive runs use `--min-spp` (default `MIN_ADAPTIVE_SPP`) as the minimum. '
    '`target_error` is the image\'s RMSE over hit pixels: the render stops when '
    'its estimate (per-pixel posterior variances, the measured Sobol efficiency) is below '
    '`RMSE_AIM` x target, doubling in each round the pixels with the most variance '
    'removed per ray (Neyman allocation). `max_pixel_error` is the per-pixel rule: every '
    'pixel\'s 95% half-width below the number.'
)


@dataclass
class Curve:
    method: str
    points: list[tuple[float, float, float]] = field(default_factory=list)  # (knob, s, rmse)

    def time_to(self, goal: float) -> float | None:
        """Seconds to reach RMSE `goal`, interpolated in log-log between sweep points."""
        pts = sorted((t, e) for _, t, e in self.points)
        for (t0, e0), (t1, e1) in zip(pts, pts[1:], strict=False):
            if e0 > goal >= e1 and e1 > 0:
                f = math.log(e0 / goal) / math.log(e0 / e1)
                return math.exp(math.log(t0) + f * math.log(t1 / t0))
        return pts[0][0] if pts and pts[0][1] <= goal else None


# --- peers: the same primary hits and occlusion directions, traced by someone else ---------


def peer_ao(peer, o, d, hits: surface.PrimaryHits, spp: int, dist: float, sampler: str,
            seed: int, progress: Callable[[int], None] | None = None) -> tuple[np.ndarray, float]:
    """Fixed-spp AO of the hit pixels with our spawn points and directions, traced by
    `peer` (a `backend.peers` tracer; `peer.threads` host threads): (AO per hit pixel, peer
    seconds, counting only its trace calls)."""
    start = time.perf_counter()
    peer.closest(o, d, threads=peer.threads)
    seconds = time.perf_counter() - start
    h = len(hits.pixels)
    n_open = np.zeros(h, dtype=np.int64)
    step = max(1, min(spp, PEER_CHUNK // max(h, 1)))
    for first in range(0, spp, step):
        count = min(step, spp - first)
        origins, dirs = tracers.occlusion_rays(hits, first, count, seed, sampler)
        start = time.perf_counter()
        blocked = peer.occluded(origins, dirs, dist, peer.threads)
        seconds += time.perf_counter() - start
        n_open += (~blocked).reshape(h, count).sum(axis=1)
        if progress:
            progress(count)
    return n_open / spp, seconds


# --- reference --------------------------------------------------------------------------


def reference(name: str, scene, bvh, o, d, tmin, tmax, dist: float, spp: int,
              cache: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(AO, Bernoulli variance of that AO, hit mask) at `spp` independent samples, traced
    by Embree; cached by scene, size, distance and spp."""
    cam = scene.camera
    key = hashlib.sha1(f"{name}|{cam.width}x{cam.height}|{dist!r}|{spp}|v1".encode()).hexdigest()
    path = cache / f"{name}_{cam.width}x{cam.height}_{spp}_{key[:10]}.npz"
    if path.is_file():
        z = np.load(path)
        return z["ao"], z["var"], z["hit"]
    t = time.perf_counter()
    hits = primary.trace_primary(bvh, o, d, tmin, tmax)
    peer = peers.Embree(scene.vertices, scene.indices)
    peer.threads = 1
    values, _ = peer_ao(peer, o, d, hits, spp, dist, "random", seed=987_654)
    full = np.ones(len(o))
    var = np.zeros(len(o))
    full[hits.pixels] = values
    var[hits.pixels] = values * (1 - values) / (spp - 1)
    hit = np.zeros(len(o), dtype=bool)
    hit[hits.pixels] = True
    cache.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, ao=full, var=var, hit=hit)
    print(f"  reference {spp} spp: {time.perf_counter() - t:.1f} s (cached at {path})")
    return full, var, hit


def raw_seconds(runs: list[ao.AoResult]) -> float:
    """Median seconds of renders, less the denoise where there was one."""
    return statistics.median(r.timings_ms.total - (r.timings_ms.denoise or 0.0)
                             for r in runs) / 1e3


def rmse(est: np.ndarray, ref: np.ndarray, var: np.ndarray, hit: np.ndarray) -> float:
    mse = float(np.mean((est[hit].astype(np.float64) - ref[hit]) ** 2) - np.mean(var[hit]))
    return math.sqrt(max(mse, 1e-12))


# --- one scene --------------------------------------------------------------------------


def run_scene(name: str, args) -> tuple[dict, list[Curve]]:
    info = shared_scene_infos()[name]
    width = args.width
    height = args.height or max(1, round(width * 3 / 4))
    scene = shared_scene(name, width, height)
    o, d, tmin, tmax = scene.camera.rays()
    t = time.perf_counter()
    bvh = kernels.build_bvh(scene.vertices, scene.indices)
    build_ours = time.perf_counter() - t
    dist = ao.default_distance(bvh)
    threads = host_threads(bvh.device, args.threads)
    print(f"{name}: {scene.triangles:,} triangles, {width}x{height}, distance {dist:.4g}")
    ref, var, hit = reference(name, scene, bvh, o, d, tmin, tmax, dist, args.ref_spp,
                              REPO / ".cache" / "ao_ref")
    spps = FIXED_SPP
    targets = QUICK_TARGETS if args.quick else TARGETS

    def measure(fn: Callable[[], tuple[np.ndarray, float]]) -> tuple[float, float]:
        runs = [fn() for _ in range(args.repeat)]
        return statistics.median(s for _, s in runs), rmse(runs[0][0], ref, var, hit)

    last: dict = {}

    def ours(**kw) -> tuple[np.ndarray, float]:
        res = kernels.render_ao(bvh, o, d, tmin=tmin, tmax=tmax, distance=dist,
                                threads=args.threads, **kw)
        last["result"] = res
        return res.ao, res.timings_ms.total / 1e3

    def render(**kw) -> ao.AoResult:
        ours(**kw)
        return last["result"]

    def point(curve: Curve, knob: float, runs: list[ao.AoResult]) -> tuple[float, float]:
        """The raw point (seconds without the denoise, RMSE) of these renders; with
        --denoise the same renders' denoised point goes on `curve`."""
        first = runs[0]
        if not args.denoise:
            return statistics.median(r.timings_ms.total for r in runs) / 1e3, rmse(
                first.ao, ref, var, hit)
        curve.points.append((knob, statistics.median(r.timings_ms.total for r in runs)
                             / 1e3, rmse(first.ao, ref, var, hit)))
        return raw_seconds(runs), rmse(first.raw_ao, ref, var, hit)

    def ours_point(curve: Curve, knob: float, **kw) -> tuple[float, float]:
        return point(curve, knob, [render(**kw, denoise=args.denoise, image_shape=(height, width))
                                   for _ in range(args.repeat)])

    def alternated(**kws: dict) -> dict[str, list[ao.AoResult]]:
        """`repeat` renders of each named configuration, in turn and in alternating order
        (a b c, c b a, ...): load that drifts during the run weighs on all of them alike."""
        runs: dict[str, list[ao.AoResult]] = {k: [] for k in kws}
        for i in range(args.repeat):
            for k in (list(kws) if i % 2 == 0 else list(kws)[::-1]):
                runs[k].append(render(**kws[k]))
        return runs

    curves = [Curve("ours sobol"), Curve("ours random"), Curve("ours target_error"),
              Curve("ours max_pixel_error")]
    if args.peers:
        curves += [Curve("wp.Mesh"), Curve("wp.Mesh 1t"), Curve("Embree")]
    denoised = [Curve("ours sobol denoised"), Curve("ours target_error denoised")]
    hits = primary.trace_primary(bvh, o, d, tmin, tmax)
    t = time.perf_counter()
    tracers = []
    if args.peers:
        mesh = peers.WarpMesh(scene.vertices, scene.indices)
        tracers = [mesh, copy.copy(mesh), peers.Embree(scene.vertices, scene.indices)]
        tracers[0].threads = threads  # our trick: its launches split between host threads
        tracers[1].threads = 1  # as Warp runs a launch on CPU
        tracers[2].threads = 1  # embreex holds the Python lock
    build_peers = time.perf_counter() - t
    for peer in tracers:  # Embree builds lazily and Warp compiles on first use: not timed
        peer_ao(peer, o[:64], d[:64], hits, 1, dist, "sobol", 0)
    ours(spp=1)
    for spp in spps:
        s, e = ours_point(denoised[0], spp, spp=spp)
        curves[0].points.append((spp, s, e))
        if not args.quick:
            s, e = measure(lambda spp=spp: ours(spp=spp, sampler="random"))
            curves[1].points.append((spp, s, e))
        for curve, peer in zip(curves[4:], tracers if spp in PEER_SPP else [], strict=False):
            def traced(peer=peer, spp=spp):
                values, s = peer_ao(peer, o, d, hits, spp, dist, "sobol", 0)
                full = np.ones(len(o))
                full[hits.pixels] = values
                return full, s
            s, e = measure(traced)
            curve.points.append((spp, s, e))
        print(f"  spp {spp:4d}: " + "  ".join(
            f"{c.method} {c.points[-1][1]:.3f}s/{c.points[-1][2]:.4f}"
            for c in curves + denoised[:1] if c.points and c.points[-1][0] == spp))
    floors = []
    for target in targets:
        adaptive = {"target_error": target, "spp": args.min_spp, "max_spp": args.max_spp}
        if target not in FLOOR_TARGETS:
            s, e = ours_point(denoised[1], target, **adaptive)
            curves[2].points.append((target, s, e))
            continue
        # The floors compare times: the render, the fewest fixed spp reaching its RMSE (the
        # cheapest: time grows with spp; picked from a first, untimed render, which the seed
        # makes the same as the timed ones) and the old rule are timed in alternation.
        first = render(**adaptive, denoise=args.denoise, image_shape=(height, width))
        e_first = rmse(first.raw_ao if args.denoise else first.ao, ref, var, hit)
        reaching = [spp for spp, _, fe in curves[0].points if fe <= e_first]
        kws = {"target": {**adaptive, "denoise": args.denoise, "image_shape": (height, width)}}
        if reaching:
            kws["fixed"] = {"spp": min(reaching)}
        if target in OLD_RULE_TARGETS:
            kws["old"] = {"max_pixel_error": target, "spp": args.min_spp,
                          "max_spp": args.max_spp}
        runs = alternated(**kws)
        s, e = point(denoised[1], target, runs["target"])
        curves[2].points.append((target, s, e))
        stats = runs["target"][0].stats()
        den = denoised[1].points[-1] if args.denoise else (None, None, None)
        print(f"  target {target:.4f}: {s:.3f}s rmse {e:.4f} ({e / target:.2f}x) "
              f"est {stats.rmse_estimate:.4f} spp {stats.spp_mean:.1f}")
        spp_fixed = kws["fixed"]["spp"] if reaching else None
        s_fixed = raw_seconds(runs["fixed"]) if reaching else None
        s_old = None
        if "old" in runs:
            s_old = raw_seconds(runs["old"])
            e_old = rmse(runs["old"][0].ao, ref, var, hit)
            curves[3].points.append((target, s_old, e_old))
            print(f"  max_pixel_error {target:.4f}: {s_old:.3f}s rmse {e_old:.4f}")
        floors.append({"target": target, "s": s, "rmse": e, "estimate": stats.rmse_estimate,
                       "spp_mean": stats.spp_mean, "spp_fixed": spp_fixed,
                       "s_fixed": s_fixed, "s_old": s_old, "s_denoised": den[1],
                       "rmse_denoised": den[2]})
    row = {"scene": name, "triangles": scene.triangles, "size": f"{width}x{height}",
           "hit": float(hit.mean()), "distance": dist, "floors": floors,
           "build_ms": {"ours": build_ours * 1e3, "peers (both)": build_peers * 1e3},
           "threads": threads, "info": info.get("file", name)}
    return row, curves + (denoised if args.denoise else [])


# --- output -----------------------------------------------------------------------------


def ratio(a: float | None, b: float | None) -> str:
    return f"{a / b:.2f}" if a is not None and b is not None else "n/a"


def dash(x: float | None, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def fmt(s: float | None) -> str:
    return f"{s:.3f}" if s is not None else "not reached"


def table(rows: list[dict], args) -> str:
    lines = [
        f"Run: `{args.command_line}` on {os.cpu_count()} cores, CPU only (load average "
        f"{args.load}); each point is the median of {args.repeat} timed runs.",
        "",
        "Floors per scene and target_error: achieved RMSE / target in "
        f"[{CALIBRATION[0]}, {CALIBRATION[1]}]; time over the fewest fixed Sobol spp whose "
        f"RMSE is at most the one achieved (the cheapest) <= {COST_FLOOR}; max_pixel_error's "
        f"time at the same number over target_error's >= {OLD_RULE_FLOOR}; the three timed "
        "in alternation, each the median of the same number of runs.",
        "",
        "Denoised: the same render's image after OIDN (its RMSE against the reference; s "
        "includes the denoise). It claims no target: the render's estimate is the raw one's.",
        "",
        "| scene | size | hit | target | RMSE | RMSE / target | estimate / RMSE | mean spp "
        "| s | cheapest fixed (spp, s) | vs fixed | max_pixel_error s | its / ours "
        "| denoised RMSE | denoised s | floors |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in rows:
        for f in r["floors"]:
            ok = floor_ok(f)
            verdict = "pass" if all(ok.values()) else "FAIL " + ", ".join(
                k for k, v in ok.items() if not v)
            fixed = f"{f['spp_fixed']}, {f['s_fixed']:.3f}" if f["s_fixed"] else "none"
            lines.append(
                f"| {r['scene']} | {r['size']} | {r['hit']:.0%} | {f['target']:g} | "
                f"{f['rmse']:.4f} | {f['rmse'] / f['target']:.2f} | "
                f"{f['estimate'] / f['rmse']:.2f} | {f['spp_mean']:.1f} | {f['s']:.3f} | "
                f"{fixed} | {ratio(f['s'], f['s_fixed'])} | "
                f"{fmt(f['s_old']) if f['s_old'] else '-'} | "
                f"{ratio(f['s_old'], f['s']) if f['s_old'] else '-'} | "
                f"{dash(f.get('rmse_denoised'), '.4f')} | {dash(f.get('s_denoised'), '.3f')} | "
                f"{verdict} |"
            )
    return "\n".join(lines)


def floor_ok(f: dict) -> dict[str, bool]:
    """Each floor of one (scene, target): calibration, cost, old rule (where measured)."""
    out = {"calibration": CALIBRATION[0] <= f["rmse"] / f["target"] <= CALIBRATION[1],
           "cost": f["s_fixed"] is not None and f["s"] <= COST_FLOOR * f["s_fixed"]}
    if f["s_old"] is not None:
        out["old rule"] = f["s_old"] >= OLD_RULE_FLOOR * f["s"]
    return out


def floor_line(rows: list[dict]) -> str:
    checks = [(r["scene"], f["target"], k, v) for r in rows for f in r["floors"]
              for k, v in floor_ok(f).items()]
    failed = [f"{sc} {t:g} {k}" for sc, t, k, v in checks if not v]
    return (f"Floors met in {len(checks) - len(failed)} of {len(checks)} checks"
            + (f"; not met: {', '.join(failed)}." if failed else "."))


def sweep_table(name: str, curves: list[Curve]) -> str:
    lines = [f"<details><summary>{name}: every point (knob, seconds, RMSE)</summary>", "",
             "| method | knob | s | RMSE |", "|---|---:|---:|---:|"]
    for c in curves:
        for k, s, e in c.points:
            lines.append(f"| {c.method} | {k:g} | {s:.3f} | {e:.4f} |")
    return "\n".join([*lines, "", "</details>"])


def plot(results: list[tuple[dict, list[Curve]]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(results)
    cols = min(n, 4)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 3.4 * rows), squeeze=False)
    styles = {"ours target_error": "o-", "ours max_pixel_error": "o--", "ours sobol": "s-",
              "ours random": "s--", "wp.Mesh": "^-", "wp.Mesh 1t": "^--", "Embree": "v-",
              "ours sobol denoised": "x:", "ours target_error denoised": "*:"}
    for ax, (row, curves) in zip(axes.ravel(), results, strict=False):
        for c in curves:
            pts = [(s, e) for _, s, e in c.points]  # in sweep order: noise shows as noise
            ax.loglog([p[0] for p in pts], [p[1] for p in pts], styles[c.method], ms=3,
                      label=c.method)
        ax.axhline(RMSE_GOAL, color="grey", lw=0.8, ls=":")
        ax.set_title(f"{row['scene']} {row['size']}")
        ax.set_xlabel("wall time (s)")
        ax.set_ylabel("RMSE")
        ax.grid(True, which="both", lw=0.3)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    axes.ravel()[0].legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def write_docs(results: list[tuple[dict, list[Curve]]], args) -> None:
    figure = REPO / "docs" / "figures" / "ao_error.png"
    plot(results, figure)
    body = "\n\n".join([
        "## Ambient occlusion: run time against error",
        "Produced by `benchmarks/ao_error.py` (method, reference and timing rules in its "
        f"docstring). RMSE over hit pixels against an independent {args.ref_spp}-spp Embree "
        "reference (its own variance removed); same spawn points and Sobol directions for "
        "every tracer. Below 512 pixels across, fixed per-launch costs weigh more than at "
        "full size.",
        ADAPTIVE_NOTE,
        table([r for r, _ in results], args),
        floor_line([r for r, _ in results]),
        "![AO time against error](figures/ao_error.png)",
        *[sweep_table(r["scene"], c) for r, c in results],
    ])
    write_section("ao_error", body)
    print(f"wrote {figure.relative_to(REPO)} and the AO section of docs/benchmarks.md")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", default=None, help="comma-separated (default: all shared)")
    parser.add_argument("--width", type=int, default=512)
    parser.add_argument("--height", type=int, default=None, help="default: width * 3/4")
    parser.add_argument("--ref-spp", type=int, default=None, help="default 4096 (quick: 1024)")
    parser.add_argument("--max-spp", type=int, default=4096, help="adaptive cap")
    parser.add_argument("--min-spp", type=int, default=options.MIN_ADAPTIVE_SPP,
                        help="adaptive minimum (the spp argument; default "
                             f"{options.MIN_ADAPTIVE_SPP})")
    parser.add_argument("--repeat", type=int, default=1, help="timed runs per point (median)")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--quick", action="store_true",
                        help="Sobol only (no random curve), the floor targets only, 1024-spp ref")
    parser.add_argument("--no-docs", action="store_true", help="print only")
    parser.add_argument("--denoise", action="store_true",
                        help="also denoised curves (needs pip install \"scenesort[denoise]\")")
    parser.add_argument("--no-peers", dest="peers", action="store_false",
                        help="ours only (no wp.Mesh or Embree curves)")
    args = parser.parse_args(argv)
    args.load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    args.command_line = " ".join(["benchmarks/ao_error.py", *(argv or sys.argv[1:])])
    args.ref_spp = args.ref_spp or (1024 if args.quick else 4096)
    wp.config.quiet = True
    wp.init()
    names = args.scenes.split(",") if args.scenes else list(shared_scene_infos())
    unknown = sorted(set(names) - set(shared_scene_infos()))
    if unknown:
        parser.error(f"unknown scenes {unknown}; shared scenes are {sorted(shared_scene_infos())}")
    results = [run_scene(name, args) for name in names]
    print(table([r for r, _ in results], args))
    if not args.no_docs:
        write_docs(results, args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
