"""Divide-and-conquer ray tracing against BVH build + trace, in the same run.

    .venv/bin/python benchmarks/dacrt.py [--scenes bunny,sponza] [--sizes 512,1024]
        [--kinds primary,ao,random,shadow,specular] [--repeat 3] [--tuning paper|cpu]
        [--figure-scene sponza --figure-size 256] [--no-docs]

Prints the 2012 paper's Table 6.3 (MRays/s of task-pool DACRT, spatial median and RDH, per
image size, for primary, ambient-occlusion (7 per primary hit) and random rays), the 2013
paper's Tables 1-3 (ms per frame of breadth-first DACRT for primary, shadow (one point light),
specular and AO rays (7 per primary hit here, 8 in the paper), and peak memory), each row
beside BVH build (binned SAH) + trace of the same rays. Every DACRT result is checked against
the BVH's (hit/miss mismatches are counted). Times are the median of --repeat runs after
one warm-up (compilation excluded); the pool variant's splits run in turn (interleaved, in
alternating order), the BVH and breadth-first each on their own. RDH against the median is
judged by the paired ratios of the rounds (see the floors). For 1024² primary rays the BVH
is also timed right after a big free (`bvh_warm_s`): on this VM that makes it up to 30%
faster (see the notes), and the floor is judged against the faster of the two.

Peak memory: DACRT counts the bytes of every device array it holds at its peak (inputs,
index arrays, pool or level lists, the terminal buffer, outputs); the BVH's figure counts the
same way from `build_bvh`'s allocations (inputs, build temporaries, the tree) plus the rays
and hits of `trace`.

Tuning: "paper" runs the papers' GPU constants (C_SORT = 80, 32 rays / 16 triangles,
alpha = beta = 256); "cpu" the constants calibrated on this CPU (C_SORT = 4, 16 rays / 16
triangles; alpha = 32, beta = 128); the pool runs one worker per core, as BVH build and
trace use every core.

Floors (CPU): RDH no slower than median on any scene at 1024^2; for 1024^2 primary rays the
faster DACRT variant within 3x of BVH build + trace.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from dataclasses import replace
from math import comb
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from docs_section import write_section  # noqa: E402  (benchmarks/ is on sys.path)
from scenesort.backend.render.scenes import shared_scene  # noqa: E402
from scenesort.backend.tools.peers import samples_each, timeit_each  # noqa: E402
from scenesort.kernels import dacrt_trace  # noqa: E402

from scenesort import kernels  # noqa: E402

AO_SPP = 7  # 2012 paper: 7 AO rays per primary ray (the 2013 paper's 8 is close)
ALL_SCENES = ("bunny", "dragon", "buddha", "blade", "sponza", "sibenik", "conference")
TUNINGS = {  # explicit both: dacrt_trace's defaults depend on the device (kernels.dacrt.options)
    "paper": {"pool": {"c_sort": 80.0, "min_rays": 32},
              "breadth_first": {"alpha": 256, "beta": 256}},
    "cpu": {"pool": {"c_sort": 4.0, "min_rays": 16},
            "breadth_first": {"alpha": 32, "beta": 128}},
}


# ---------------------------------------------------------------- rays


def scene_rays(scene, size: int, kind: str, ref, rng) -> tuple[np.ndarray, ...]:
    """(origins, directions, tmin, tmax) of one ray kind; secondary rays start at the BVH's
    primary hits, offset along the geometric normal."""
    o, d, tmin, tmax = replace(scene.camera, width=size, height=size).rays()
    if kind == "primary":
        return o, d, tmin, tmax
    v = scene.vertices.astype(np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    diag = float(np.linalg.norm(hi - lo))
    if kind == "random":  # 2012 paper: uniformly in the scene box, uniform directions
        n = len(o)
        orig = lo + (hi - lo) * rng.random((n, 3))
        dirs = rng.normal(size=(n, 3))
        return _f32(orig), _f32(dirs), np.zeros(n, np.float32), np.full(n, np.inf, np.float32)
    hit = ref.triangle >= 0
    tri = v[scene.indices[ref.triangle[hit]]]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
    dh = d[hit].astype(np.float64)
    nrm *= -np.sign(np.einsum("ij,ij->i", nrm, dh))[:, None]  # face the viewer
    p = o[hit] + ref.t[hit, None].astype(np.float64) * dh + 1e-4 * diag * nrm
    if kind == "shadow":  # one point light above the scene's centre
        light = (lo + hi) / 2 + 0.45 * (hi - lo) * scene_up(scene)
        dirs = light - p
        dist = np.linalg.norm(dirs, axis=1)
        return _f32(p), _f32(dirs / dist[:, None]), np.zeros(len(p), np.float32), _f32(dist)
    if kind == "specular":
        dirs = dh - 2 * np.einsum("ij,ij->i", dh, nrm)[:, None] * nrm
        return _f32(p), _f32(dirs), np.zeros(len(p), np.float32), np.full(len(p), np.inf,
                                                                         np.float32)
    p = np.repeat(p, AO_SPP, axis=0)
    nrm = np.repeat(nrm, AO_SPP, axis=0)
    dirs = _cosine_hemisphere(nrm, rng)
    dist = np.full(len(p), 0.1 * diag, np.float32)
    return _f32(p), _f32(dirs), np.zeros(len(p), np.float32), dist


def scene_up(scene) -> np.ndarray:
    return np.array([0.0, 0.0, 1.0]) if scene.name == "blade" else np.array([0.0, 1.0, 0.0])


def _cosine_hemisphere(n: np.ndarray, rng) -> np.ndarray:
    u1, u2 = rng.random(len(n)), rng.random(len(n))
    r, phi = np.sqrt(u1), 2 * np.pi * u2
    local = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1 - u1)], axis=1)
    a = np.where(np.abs(n[:, :1]) > 0.9, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    x = np.cross(a, n)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(n, x)
    return local[:, :1] * x + local[:, 1:2] * y + local[:, 2:] * n


def _f32(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32)


# ---------------------------------------------------------------- measuring


def bvh_peak_bytes(bvh, rays: int) -> int:
    """`build_bvh`'s allocations (inputs, temporaries, tree) plus `trace`'s rays and hits."""
    m = bvh.stats.triangles
    n = m - bvh.stats.degenerate
    capacity = 256
    build = (len(bvh.vertices) * 12 + m * 12 + 3 * m * 12 + n * (4 + 3 * 4 + 1 + 4 * 12)
             + capacity * 96 * 28 + capacity * 256 + (2 * n - 1) * 32 + 9 * n * 4)
    return int(build + rays * (2 * 12 + 2 * 4 + 4 * 4))


def timed(fn, repeat: int):
    fn()  # warm-up: compilation and caches
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def mismatches(h, ref) -> int:
    return int(np.count_nonzero((h.triangle >= 0) != (ref.triangle >= 0)))


def free_big(nbytes: int = 1 << 29) -> None:
    """Touch and free `nbytes`: a call right after this finds the kernel's memory in the
    state that a big free leaves (on this VM: up to 30% faster for BVH build + trace)."""
    a = np.ones(nbytes // 8)
    del a


def measure(scene, size: int, kind: str, methods: list[str], tuning: str, repeat: int, rng):
    ref_primary = kernels.trace(kernels.build_bvh(scene.vertices, scene.indices),
                                *replace(scene.camera, width=size, height=size).rays())
    o, d, tmin, tmax = scene_rays(scene, size, kind, ref_primary, rng)
    row = {"scene": scene.name, "tris": scene.triangles, "size": size, "kind": kind,
           "rays": len(o), "tuning": tuning}
    last: dict = {}  # each method's latest result
    stats = {m: kernels.DacrtStats() for m in methods}

    def bvh_run():
        bvh = kernels.build_bvh(scene.vertices, scene.indices)
        last["bvh"] = bvh, kernels.trace(bvh, o, d, tmin, tmax)

    def dacrt_run(method: str):
        variant, split = ("breadth_first", "rdh") if method == "bf" else ("pool", method)
        last[method] = dacrt_trace(scene.vertices, scene.indices, o, d, tmin, tmax,
                                   variant=variant, split=split, stats=stats[method],
                                   **TUNINGS[tuning][variant])

    # The splits interleaved, so that a burst of load hits both alike; the BVH and
    # breadth-first apart: what they leave behind changes the next call's time (notes)
    pool = [m for m in methods if m != "bf"]
    times = timeit_each([bvh_run], repeat)
    samples = samples_each([lambda m=m: dacrt_run(m) for m in pool], repeat)
    times += [float(np.median(x)) for x in samples]
    if {"median", "rdh"} <= set(pool):  # paired: the two splits of one round, side by side
        row["rdh_median_ratios"] = [r / m for r, m in zip(samples[pool.index("rdh")],
                                                            samples[pool.index("median")],
                                                            strict=True)]
    if "bf" in methods:
        times += timeit_each([lambda: dacrt_run("bf")], repeat)
    if size >= 1024 and kind == "primary":
        row["bvh_warm_s"] = timeit_each([bvh_run], repeat, before=free_big)[0]
    bvh, ref = last["bvh"]
    row["bvh_s"] = times[0]
    row["bvh_build_ms"] = bvh.stats.build_ms
    row["bvh_peak_mb"] = bvh_peak_bytes(bvh, len(o)) / 2**20
    for method, t in zip(pool + [m for m in methods if m == "bf"], times[1:], strict=True):
        row[f"{method}_s"] = t
        row[f"{method}_mismatch"] = mismatches(last[method], ref)
        row[f"{method}_peak_mb"] = stats[method].peak_bytes / 2**20
    print(json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()}),
          flush=True)
    return row


# ---------------------------------------------------------------- tables


def table_2012(rows: list[dict]) -> str:
    head = ("| scene | tris | size | rays | kind | constants | median MRays/s | RDH MRays/s | "
            "BVH build+trace MRays/s | RDH / median time | RDH / BVH time | mismatches |\n"
            "|---|---:|---:|---:|---|---|---:|---:|---:|---:|---:|---:|")
    lines = [head]
    for r in rows:
        if "median_s" not in r:
            continue
        mr = r["rays"] / 1e6
        lines.append(
            f"| {r['scene']} | {r['tris']:,} | {r['size']}² | {r['rays']:,} | {r['kind']} | "
            f"{r['tuning']} | {mr / r['median_s']:.3f} | {mr / r['rdh_s']:.3f} | "
            f"{mr / r['bvh_s']:.3f} | "
            f"{r['rdh_s'] / r['median_s']:.2f} | {r['rdh_s'] / r['bvh_s']:.2f} | "
            f"{r['median_mismatch'] + r['rdh_mismatch']} |")
    return "\n".join(lines)


def table_2013(rows: list[dict]) -> str:
    head = ("| scene | size | kind | rays | constants | breadth-first ms | pool RDH ms | "
            "BVH build+trace ms | BF peak MB | pool peak MB | BVH peak MB | mismatches |\n"
            "|---|---:|---|---:|---|---:|---:|---:|---:|---:|---:|---:|")
    lines = [head]
    for r in rows:
        if "bf_s" not in r:
            continue
        pool = f"{1e3 * r['rdh_s']:.0f}" if "rdh_s" in r else "-"
        pool_mb = f"{r['rdh_peak_mb']:.1f}" if "rdh_peak_mb" in r else "-"
        lines.append(
            f"| {r['scene']} | {r['size']}² | {r['kind']} | {r['rays']:,} | {r['tuning']} | "
            f"{1e3 * r['bf_s']:.0f} | {pool} | {1e3 * r['bvh_s']:.0f} | {r['bf_peak_mb']:.1f} | "
            f"{pool_mb} | {r['bvh_peak_mb']:.1f} | {r['bf_mismatch']} |")
    return "\n".join(lines)


def median_interval(x: list[float], level: float = 0.9) -> tuple[float, float, float]:
    """(low, high, coverage): the distribution-free interval [x(k), x(n+1-k)] of the sorted
    values that holds their population median with probability `coverage` >= level (the
    sign test's order statistics); [min, max] if even that falls short (n < 5)."""
    n = len(x)
    xs = sorted(x)

    def coverage(k: int) -> float:
        return 1 - 2 * sum(comb(n, j) for j in range(k)) / 2**n

    k = 1
    while k < n // 2 and coverage(k + 1) >= level:
        k += 1
    return xs[k - 1], xs[n - k], coverage(k)


def verdict(lo: float, hi: float) -> str:
    """'faster', 'tie' or 'slower' for an interval of RDH / median time ratios."""
    return "slower" if lo > 1.0 else "faster" if hi < 1.0 else "tie"


def floors(rows: list[dict]) -> str:
    out = []
    big = [r for r in rows if r["size"] >= 1024 and "rdh_median_ratios" in r]
    if big:
        for tuning in sorted({r["tuning"] for r in big}):
            rows_t = [r for r in big if r["tuning"] == tuning]
            parts, slower = [], 0
            for r in rows_t:
                x = r["rdh_median_ratios"]
                lo, hi, cover = median_interval(x)
                slower += verdict(lo, hi) == "slower"
                parts.append(f"{r['scene']} {statistics.median(x):.3f} [{lo:.3f}, {hi:.3f}] "
                             f"{verdict(lo, hi)}")
            out.append(f"- RDH no slower than median at 1024², {tuning} constants (median of "
                       f"the {len(x)} paired RDH / median time ratios, {100 * cover:.0f}% "
                       f"interval): {'PASS' if not slower else 'FAIL'} "
                       f"({len(rows_t) - slower} of {len(rows_t)} rows not slower): "
                       + "; ".join(parts))
    prim = [r for r in rows if r["size"] >= 1024 and r["kind"] == "primary"]
    for r in prim:
        best = min(r.get(k, np.inf) for k in ("rdh_s", "median_s", "bf_s"))
        bvh = min(r["bvh_s"], r.get("bvh_warm_s", np.inf))
        ratio = best / bvh
        out.append(f"- {r['scene']} 1024² primary, {r['tuning']} constants: fastest DACRT / "
                   f"(BVH build + trace) = {ratio:.2f} against the faster BVH time "
                   f"({best / r['bvh_s']:.2f} against the other one) "
                   f"({'PASS' if ratio <= 3 else 'FAIL'} at 3x)")
    if not out:
        out.append("- floors need 1024² rows: not measured in this run")
    return "\n".join(out)


def figure(scene, size: int, tuning: str, path: Path, rng) -> list[tuple]:
    """2012 paper, Figure 6.4: time against the number of AO rays (1, 2, 4, 8 per pixel)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ref = kernels.trace(kernels.build_bvh(scene.vertices, scene.indices),
                        *replace(scene.camera, width=size, height=size).rays())
    o1, d1, tmin1, tmax1 = scene_rays(scene, size, "ao", ref, rng)
    points = []
    for spp in (1, 2, 4, 7):
        keep = np.arange(len(o1)).reshape(-1, 7)[:, :spp].ravel()
        o, d, tmin, tmax = o1[keep], d1[keep], tmin1[keep], tmax1[keep]
        kw: dict = TUNINGS[tuning]
        t_rdh, _ = timed(lambda o=o, d=d, tmin=tmin, tmax=tmax, kw=kw: dacrt_trace(
            scene.vertices, scene.indices, o, d, tmin, tmax, **kw["pool"]), 1)
        t_bf, _ = timed(lambda o=o, d=d, tmin=tmin, tmax=tmax, kw=kw: dacrt_trace(
            scene.vertices, scene.indices, o, d, tmin, tmax, variant="breadth_first",
            **kw["breadth_first"]), 1)
        t_bvh, _ = timed(lambda o=o, d=d, tmin=tmin, tmax=tmax: kernels.trace(
            kernels.build_bvh(scene.vertices, scene.indices), o, d, tmin, tmax), 1)
        points.append((len(o), t_rdh, t_bf, t_bvh))
        print(json.dumps({"figure": scene.name, "rays": len(o), "rdh_s": round(t_rdh, 3),
                          "bf_s": round(t_bf, 3), "bvh_s": round(t_bvh, 3)}), flush=True)
    fig, ax = plt.subplots(figsize=(6, 4))
    x = [p[0] / 1e6 for p in points]
    for k, label in ((1, "task-pool DACRT, RDH"), (2, "breadth-first DACRT"),
                     (3, "BVH build + trace")):
        ax.plot(x, [p[k] for p in points], "o-", label=label)
    ax.set_xlabel("AO rays (millions)")
    ax.set_ylabel("time (s)")
    ax.set_title(f"{scene.name} {size}², AO rays 1-7 per pixel ({tuning} constants)")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    return points


NOTES = """\
Notes (what the numbers mean):

- **Exactness.** Every DACRT row is compared with `kernels.trace` on the same rays: hit/miss
  must be identical ("mismatches"); the tests also check t to 1e-6 and the triangle (a
  different one only at equal t).
- **Constants.** The papers' values (C_SORT = 80, intersection tasks below 32 rays or 16
  triangles, alpha = beta = 256) fit a GPU warp of 32 threads. On one CPU thread a sorting
  step per item costs a few intersection tests, so the pool variant does better with
  C_SORT = 4 and 16 rays; breadth-first with alpha = 32, beta = 128. Both were picked from
  short sweeps on Sponza and the bunny at 512² and 1024² (e.g. Sponza 512² RDH: 1.31 s with
  C_SORT = 4 against 3.6 s with 80; breadth-first 1.6 s with 32/128 against 4.1 s with
  256/256). `--tuning paper` runs the papers' values beside them.
- **Workers and small tasks.** The pool runs one worker per core, like BVH build and trace.
  A task of at most `small_items` rays + triangles sorts in one worker: classification, a
  counting sort into the seven children's interval layout and the triangle boxes in one
  phase ("Sort") instead of PPS1, Swap1, PPS2, Swap2 and AABB with their scans and steps.
  On CPU `small_items` is a worker's share of all rays and triangles (at least 32768), so
  with two workers only the root runs the paper's phases, in parallel. `small_items=0`
  gives the paper's phases in every task (the tests run both paths).
- **RDH.** Two sampling steps: sqrt(#tris) triangles give each candidate's two child boxes,
  then sqrt(#rays) rays (one in each of sqrt(n) equal strata of the task's interval, at a
  hashed place in it) count the hits on those boxes; cost = pairs + C_SORT x (items of both
  children). The spatial median is a 33rd candidate that a sampled candidate must beat by
  40%, and tasks with fewer than `rdh_min_rays` (4096) rays take the median directly.
- **RDH against the median.** The floor's "no slower" is judged by paired runs: each round
  runs the median and RDH back to back (in alternating order), and a row counts as slower
  only when the sign-test interval of the paired ratios lies above 1. On the object scenes
  it is a tie: RDH keeps the median in two thirds to four fifths of the tasks it samples
  there, and where it does not, its tree sorts 4-5% fewer rays but tests about as many
  ray-triangle pairs. The cost of two hypothetical leaves (pairs + C_SORT x items) does not
  see the early termination that the median's splits of the longest axis get from the
  near-first order (rays that hit in the near child are clipped in the far one).
- **Early termination.** A ray whose closest hit so far lies before its entry into a node's
  box is clipped there (in PPS1 and in intersection tasks); the seven-child order lets
  straddling rays meet near triangles before far ones. Breadth-first has no such cut
  (2013 paper, sec. 3.3).
- **Where the time goes** (Sponza 1024², RDH, cpu constants, two workers, 0.75 s of tracing):
  rays are sorted about 49 times each (51.2 M ray classifications, 2.6 M triangle ones);
  Sort 44%, intersection 33%, the root's PPS1 to Swap2 20%, SplitPlane 3%. A third of the
  ray classifications end in "clipped" (26%: the ray already hit nearer, in a task that ran
  earlier), and 77% of the rays that intersection tasks meet need no pair. Indoor cameras
  (Sponza, Sibenik, Conference) are the hard case: every ray straddles the first planes.
  Per item the sort costs about 13 ns on one core and a pair test about 6 ns (scalar code:
  Warp's CPU back end runs one ray per loop iteration; Woop's test indexes the vertices by
  the ray's axis permutation, which goes through the stack); a BVH ray visits a few dozen
  boxes and a handful of triangles, so on a CPU DACRT stays about 2x behind BVH build +
  trace.
- **Order of the timed calls.** On this VM the time of BVH build + trace depends on what
  ran before it: right after a big free (a breadth-first run, or touching and freeing
  0.5-1 GiB) it is up to 30% faster than after a pause or after its own previous call
  (buddha 1024²: 0.10 s against 0.14 s), while DACRT gains nothing; and at 512² a DACRT call
  right after a BVH call takes about 20% longer than one after another DACRT call. So the
  two splits run interleaved with each other, the BVH and breadth-first each on their own,
  and for 1024² primary rays the BVH is timed once more right after a 0.5 GiB free: the
  floor takes the faster BVH time (conservative).
- **Memory.** The pool variant holds per-slot arrays for 4096 slots (~11 MB) plus about 60 B
  per ray and 100 B per triangle; breadth-first holds the level lists (ray ids duplicated
  where rays straddle) and the terminal buffer (40 B per entry, at most 2 x (rays + tris)
  entries); the BVH column counts `build_bvh`'s temporaries and tree plus the rays and hits.
- **Rerun.** The command in this section's first lines writes it (every scene and ray kind:
  long); `--scenes`, `--sizes` and `--kinds` narrow it down, `--no-docs` only prints.
"""


def write_docs(rows: list[dict], args, command: str) -> None:
    body = "\n\n".join([
        "## Divide-and-conquer ray tracing",
        "Produced by `benchmarks/dacrt.py` (ray kinds, memory accounting and tuning in its "
        f"docstring). Run: `{command}` on 2 CPU cores of a VM: medians of interleaved runs, "
        "the splits paired in alternating order; rows still move by +-5-10% between runs.",
        "Constants: " + "; ".join(f"**{t}** = `{json.dumps(TUNINGS[t])}`"
                                  for t in sorted({*args.tuning.split(","),
                                                   *args.tuning_1024.split(",")})) + ".",
        "### 2012 paper, Table 6.3: task-pool DACRT (MRays/s)",
        table_2012(rows),
        "### 2013 paper, Tables 1-3: breadth-first DACRT (ms per frame, peak memory)",
        table_2013(rows),
        "### Floors",
        floors(rows),
        NOTES,
        "![time against AO ray count](figures/dacrt_time_vs_rays.png)"
        if (REPO / "docs/figures/dacrt_time_vs_rays.png").is_file() else "",
    ])
    write_section("dacrt", body)
    print("wrote the DACRT section of docs/benchmarks.md")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenes", default=",".join(ALL_SCENES))
    p.add_argument("--sizes", default="512,1024")
    p.add_argument("--kinds", default="primary,ao,random,shadow,specular")
    p.add_argument("--methods", default="median,rdh,bf", help="pool splits and bf")
    p.add_argument("--tuning", default="cpu", help="comma list of " + ", ".join(TUNINGS))
    p.add_argument("--tuning-1024", default="cpu", help="constants at sizes >= 1024")
    p.add_argument("--kinds-1024", default="primary",
                   help="ray kinds at sizes >= 1024 (the floors need primary)")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--figure-scene", default="sponza")
    p.add_argument("--figure-size", type=int, default=256)
    p.add_argument("--no-figure", action="store_true")
    p.add_argument("--no-docs", action="store_true")
    p.add_argument("--json", type=Path, help="also write the rows here")
    args = p.parse_args()
    rng = np.random.default_rng(0)
    methods = args.methods.split(",")
    rows = []
    for name in args.scenes.split(","):
        scene = shared_scene(name)
        for size in (int(s) for s in args.sizes.split(",")):
            kinds = args.kinds_1024 if size >= 1024 else args.kinds
            for kind in kinds.split(","):
                # 2012's table has primary/ao/random for both splits; 2013's shadow/specular
                # rows need only breadth-first (the pool RDH beside it for comparison)
                ms = methods if kind in ("primary", "ao", "random") else [
                    m for m in methods if m in ("rdh", "bf")]
                tunings = args.tuning_1024 if size >= 1024 else args.tuning
                for tuning in tunings.split(","):
                    rows.append(measure(scene, size, kind, ms, tuning, args.repeat, rng))
    if not args.no_figure:
        figure(shared_scene(args.figure_scene), args.figure_size, args.tuning.split(",")[-1],
               REPO / "docs/figures/dacrt_time_vs_rays.png", rng)
    print(table_2012(rows), table_2013(rows), floors(rows), sep="\n\n")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    if not args.no_docs:
        write_docs(rows, args, "benchmarks/dacrt.py " + " ".join(sys.argv[1:]))


if __name__ == "__main__":
    main()
