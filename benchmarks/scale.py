"""How the BVH build and the trace scale with the scene: generated scenes of 1M and 4M
triangles (16M with --huge), each a gallery of copies of the shared statues (dragon and
buddha, 100k triangles each), every copy turned by its own angle about the up axis and set
on a square grid, so no two copies share a box. Nothing is downloaded.

    .venv/bin/python benchmarks/scale.py [--huge] [--repeat 3] [--size 512] [--threads 2]
    .venv/bin/python benchmarks/scale.py --quick --json /tmp/scale.json   # a smoke run

Per scene, in a process of its own (so that its memory figures are its own):
  build     SAH, leaf 8, the device's default width (the wide collapse included), on
            `--threads` workers: median ms of --repeat builds after the first (Warp's compile
            time apart: a small build runs before anything is measured), Mtris/s, SAH cost
  memory    the first build's peak resident-set growth (Linux VmHWM, reset just before it,
            over the RSS before it) per triangle, what stays resident after it, and the BVH's
            own bytes per triangle (`BvhStats.bvh_bytes`)
  trace     primary rays (a camera over the gallery at size x size) and AO any-hit rays (4
            cosine rays per primary hit, tmax 0.1 x the scene's diagonal), MRays/s, ours on
            `--threads` host threads against embreex on as many Python threads (one share
            of the rays each: embreex traces without the Python lock), timed interleaved
  embree    embreex's build (its mesh copy included, which is most of it)

Prints a table, writes docs/figures/scale.json and docs/figures/scale.png (cost against
size) and the scale section of docs/benchmarks.md (not with --quick, --json or --no-docs).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
FIGURES = ROOT / "docs" / "figures"
SIZES = (1_000_000, 4_000_000)
HUGE = 16_000_000  # --huge: about 8 GB at the peak of its build
STATUES = ("dragon", "buddha")
QUICK_STATUES = ("bunny",)  # --quick: two bunnies, 139k triangles
AO_PER_HIT = 4
WARM_UP = 5000  # triangles of the build that runs first
SPACING = 1.3  # grid pitch over a statue's largest horizontal extent


def rss_kib(field: str) -> int:
    """A figure of /proc/self/status in KiB (VmRSS: resident now; VmHWM: its peak)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"/proc/self/status has no {field} (Linux only)")


def reset_peak() -> None:
    """Set VmHWM to the current RSS (Linux >= 4.0: clear_refs 5)."""
    Path("/proc/self/clear_refs").write_text("5")


def unit_statue(vertices: np.ndarray) -> np.ndarray:
    """The statue moved to stand on y = 0 around the y axis and scaled to height 1."""
    v = vertices.astype(np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    v -= [(lo[0] + hi[0]) / 2, lo[1], (lo[2] + hi[2]) / 2]
    return v / (hi[1] - lo[1])


def gallery(target: int, statues: tuple[str, ...], seed: int = 0
            ) -> tuple[np.ndarray, np.ndarray, int]:
    """Copies of the statues, in turn, until they hold at least `target` triangles, each
    turned about +y by a random angle, on a square grid; (vertices, indices, copies)."""
    from scenesort.backend.render.scenes import shared_scene

    meshes = [(unit_statue(s.vertices), s.indices)
              for s in (shared_scene(name) for name in statues)]
    per_pair = sum(len(f) for _, f in meshes)
    copies = max(2, round(target / per_pair * len(meshes)))
    side = math.ceil(math.sqrt(copies))
    pitch = SPACING * max(np.abs(v[:, [0, 2]]).max() * 2 for v, _ in meshes)
    rng = np.random.default_rng(seed)
    vs, fs, base = [], [], 0
    for k in range(copies):
        v, f = meshes[k % len(meshes)]
        a = rng.uniform(0, 2 * np.pi)
        c, s = np.cos(a), np.sin(a)
        turned = np.column_stack([c * v[:, 0] + s * v[:, 2], v[:, 1], -s * v[:, 0] + c * v[:, 2]])
        vs.append((turned + [pitch * (k % side), 0.0, pitch * (k // side)]).astype(np.float32))
        fs.append(f + base)
        base += len(v)
    return np.concatenate(vs), np.concatenate(fs).astype(np.int32), copies


def camera_rays(vertices: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """A camera above one corner of the gallery looking at its middle, size x size rays."""
    from scenesort.kernels import Camera

    lo, hi = vertices.min(axis=0).astype(np.float64), vertices.max(axis=0).astype(np.float64)
    mid = (lo + hi) / 2
    extent = float(max(hi[0] - lo[0], hi[2] - lo[2]))
    eye = [lo[0] - 0.15 * extent, 0.45 * extent, lo[2] - 0.15 * extent]
    cam = Camera.look_at(eye, [mid[0], 0.0, mid[2]], [0, 1, 0], 50.0, size, size)
    o, d, _, _ = cam.rays()
    return o, d


def spread(samples: list[float]) -> dict:
    return {"median": statistics.median(samples), "min": min(samples), "max": max(samples)}


def measure(target: int, statues: tuple[str, ...], repeat: int, size: int,
            threads: int) -> dict:
    """Child mode: one scene's figures (module docstring)."""
    import warp as wp

    wp.config.quiet = True
    from embree_threads import ThreadedEmbree
    from scenesort.backend.tools import peers
    from scenesort.kernels.render import default_distance

    from scenesort import kernels

    v, f, copies = gallery(target, statues)
    # compile and warm up on a few triangles: a build as large as the scene would leave its
    # freed memory to the allocator, and the measured build would reuse it unseen
    kernels.build_bvh(v, f[:WARM_UP], workers=threads)
    before = rss_kib("VmRSS")
    reset_peak()
    bvh = kernels.build_bvh(v, f, workers=threads)
    kept = rss_kib("VmRSS")
    peak = rss_kib("VmHWM")  # read second: the kernel takes it as at least the RSS now
    first = bvh.stats
    builds = []
    for _ in range(repeat):
        builds.append(kernels.build_bvh(v, f, workers=threads).stats.build_ms)

    o, d = camera_rays(v, size)
    hits = kernels.trace(bvh, o, d, threads=threads)
    ao_o, ao_d = peers.ao_rays(v, f, o, d, hits.t, hits.triangle, per_hit=AO_PER_HIT)
    dist = default_distance(bvh)
    embree = ThreadedEmbree(v, f, threads)
    rays = {}
    for kind, (ro, rd, tmax, any_hit) in {"primary": (o, d, np.inf, False),
                                          "ao": (ao_o, ao_d, dist, True)}.items():
        def theirs(ro=ro, rd=rd, tmax=tmax, any_hit=any_hit):
            if any_hit:
                return embree.occluded(ro, rd, tmax, threads)
            return embree.closest(ro, rd, threads) >= 0

        samples = peers.samples_each([
            lambda ro=ro, rd=rd, tmax=tmax, a=any_hit:
                kernels.trace(bvh, ro, rd, tmax=tmax, any_hit=a, threads=threads),
            theirs], max(repeat, 3))
        ours = kernels.trace(bvh, ro, rd, tmax=tmax, any_hit=any_hit).triangle >= 0
        rays[kind] = {"count": len(ro), "ours": spread([len(ro) / t / 1e6 for t in samples[0]]),
                      "embree": spread([len(ro) / t / 1e6 for t in samples[1]]),
                      "hit_miss_diff": int((ours != theirs()).sum())}
    return {
        "target": target, "triangles": len(f), "copies": copies, "statues": list(statues),
        "threads": threads, "build_ms": spread(builds),
        "mtris_s": len(f) / statistics.median(builds) / 1e3,
        "first_build_ms": first.build_ms, "phase_ms": first.phase_ms,
        "sah_cost": first.sah_cost, "depth": first.depth, "width": first.width,
        "bvh_bytes_per_tri": first.bvh_bytes / len(f),
        "peak_growth_per_tri": (peak - before) * 1024 / len(f),
        "kept_growth_per_tri": (kept - before) * 1024 / len(f),
        "embree_build_ms": embree.build_s * 1e3, "rays": rays, "size": size,
    }


def run_child(target: int, args: argparse.Namespace) -> dict:
    cmd = [sys.executable, __file__, "--child", str(target), "--repeat", str(args.repeat),
           "--size", str(args.size), "--threads", str(args.threads)]
    if args.quick:
        cmd.append("--quick")
    out = subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=ROOT)
    return json.loads(out.stdout.strip().splitlines()[-1])


def markdown(rows: list[dict], command: str, load: str) -> str:
    t = rows[0]["threads"]
    out = [
        f"Command: `{command}` on {platform.machine()} with {os.cpu_count()} cores, CPU only, "
        f"load before the run: {load}. Each scene ran in a process of its own. Build: SAH, "
        f"leaf 8, width {rows[0]['width']} (the collapse included), {t} workers, median "
        "[min, max] of the builds after the first; memory from the first build. Trace: "
        f"ours on {t} host threads against embreex on {t} Python threads, median [min, max] "
        f"MRays/s, interleaved; {rows[0]['size']}² camera rays, {AO_PER_HIT} AO any-hit rays "
        "per hit (tmax 0.1 x diagonal). Embree build includes embreex's mesh copy.", "",
        "| triangles | build ms | Mtris/s | SAH cost | BVH B/tri | peak growth B/tri | "
        "kept B/tri | Embree build ms | primary ours | primary Embree | AO ours | AO Embree "
        "| hit/miss diff (primary, AO) |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"]

    def cell(s: dict, fmt: str = ".2f") -> str:
        return f"{s['median']:{fmt}} [{s['min']:{fmt}}, {s['max']:{fmt}}]"

    for r in rows:
        p, a = r["rays"]["primary"], r["rays"]["ao"]
        out.append(
            f"| {r['triangles']:,} | {cell(r['build_ms'], '.0f')} | {r['mtris_s']:.2f} | "
            f"{r['sah_cost']:.1f} | {r['bvh_bytes_per_tri']:.0f} | "
            f"{r['peak_growth_per_tri']:.0f} | {r['kept_growth_per_tri']:.0f} | "
            f"{r['embree_build_ms']:.0f} | {cell(p['ours'])} | {cell(p['embree'])} | "
            f"{cell(a['ours'])} | {cell(a['embree'])} | {p['hit_miss_diff']}, "
            f"{a['hit_miss_diff']} |")
    out += ["", "Build phases of the first build (ms): " + "; ".join(
        f"{r['triangles']:,}: " + ", ".join(f"{k} {v:.0f}" for k, v in r["phase_ms"].items())
        for r in rows)]
    return "\n".join(out) + "\n"


def plot(rows: list[dict], path: Path) -> None:
    """Cost against size: build ns per triangle, bytes per triangle, and ns per ray."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = [r["triangles"] / 1e6 for r in rows]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    axes[0].plot(n, [r["build_ms"]["median"] * 1e6 / r["triangles"] for r in rows], "o-",
                 label="build (ours)")
    axes[0].plot(n, [r["embree_build_ms"] * 1e6 / r["triangles"] for r in rows], "s--",
                 label="embreex build (mesh copy incl.)")
    axes[0].set_ylabel("ns per triangle")
    axes[1].plot(n, [r["peak_growth_per_tri"] for r in rows], "o-", label="peak RSS growth")
    axes[1].plot(n, [r["kept_growth_per_tri"] for r in rows], "^-", label="kept after build")
    axes[1].plot(n, [r["bvh_bytes_per_tri"] for r in rows], "s--", label="BVH arrays")
    axes[1].set_ylabel("bytes per triangle")
    for kind, mark in (("primary", "o"), ("ao", "^")):
        for who, style in (("ours", "-"), ("embree", "--")):
            axes[2].plot(n, [1e3 / r["rays"][kind][who]["median"] for r in rows],
                         mark + style, label=f"{kind} {who}")
    axes[2].set_ylabel("ns per ray")
    for ax in axes:
        ax.set_xscale("log")
        ax.set_xlabel("triangles (millions)")
        ax.set_ylim(bottom=0)
        ax.legend(fontsize=8)
    fig.suptitle(f"Cost against scene size ({rows[0]['threads']} threads)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--huge", action="store_true", help="also the 16M-triangle scene")
    parser.add_argument("--quick", action="store_true",
                        help="a smoke run: two bunnies, 64² rays, one repeat; no docs")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--size", type=int, default=512, help="camera rays: size x size")
    parser.add_argument("--threads", type=int, default=os.cpu_count())
    parser.add_argument("--json", type=Path, help="write the figures here (no docs)")
    parser.add_argument("--no-docs", action="store_true", help="print only")
    parser.add_argument("--child", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.quick:
        args.repeat, args.size = 1, 64
    if args.child is not None:
        row = measure(args.child, QUICK_STATUES if args.quick else STATUES, args.repeat,
                      args.size, args.threads)
        print(json.dumps(row))
        return 0
    command = "python benchmarks/scale.py " + " ".join(argv if argv is not None else
                                                       sys.argv[1:])
    load = "{:.2f}, {:.2f}, {:.2f} (1, 5, 15 min)".format(*os.getloadavg())
    sizes = (1,) if args.quick else SIZES + ((HUGE,) if args.huge else ())
    rows = []
    for target in sizes:
        rows.append(run_child(target, args))
        print(f"{rows[-1]['triangles']:,} triangles: done", file=sys.stderr, flush=True)
    text = markdown(rows, command.strip(), load)
    from rich.console import Console
    from rich.markdown import Markdown

    Console(width=220).print(Markdown(text))
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1))
    elif not (args.quick or args.no_docs):
        sys.path.insert(0, str(Path(__file__).parent))
        from docs_section import write_section

        write_section("scale", "## Scale: 1M to 16M triangles (`benchmarks/scale.py`)\n\n"
                      + text + "\n![cost against size](figures/scale.png)\n")
        FIGURES.mkdir(parents=True, exist_ok=True)
        (FIGURES / "scale.json").write_text(json.dumps(rows, indent=1))
        plot(rows, FIGURES / "scale.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
