"""The BVH build against tinybvh's on the same machine, threads and scene (issue 35, item 2).

    .venv/bin/python benchmarks/peer_build.py --tinybvh ../tinybvh/tiny_bvh.h
        [--sizes 1000000,4000000] [--threads 1,2] [--rounds 3] [--repeat 2]

tinybvh (https://github.com/jbikker/tinybvh, MIT) is not a dependency and nothing is
downloaded: pass the `tiny_bvh.h` of a clone. `benchmarks/peer_build.cpp` is compiled against
it (g++ -O3 -march=native) once per header. Scenes are scale.py's galleries of the shared
statues.

Per size and thread count, --rounds rounds in alternating order: scenesort's build in this
process (SAH, leaf 8, the wide collapse and leaf blocks included: the tree its CPU traversal
uses) and two tinybvh processes, `BuildAVX` (its fastest builder: 8 bins on three axes, a
binary tree only) and `BVH8_CPU::Build` (BuildAVX, then the 8-wide tree and leaf blocks its
CPU traversal uses); each takes the median of --repeat builds after a warm-up build (Warp's
compile time apart). tinybvh runs on as many cores as scenesort has workers (`taskset`;
its threaded build above one). Prints the table with Mtris/s, SAH cost (both the binary
tree's, traversal and intersection cost 1) and the ratios, and writes its section of
docs/benchmarks.md and docs/figures/peer_build.json (not with --no-docs).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from docs_section import write_section  # noqa: E402
from scale import STATUES, WARM_UP, gallery  # noqa: E402

FIGURES = HERE.parent / "docs" / "figures"
PEERS = ("avx", "bvh8")
PEER_NAMES = {"avx": "tinybvh BuildAVX (binary)", "bvh8": "tinybvh BVH8_CPU (build + 8-wide)"}


def compile_harness(header: Path, work: Path) -> Path:
    """peer_build.cpp against `header`, compiled once per header and source."""
    source = HERE / "peer_build.cpp"
    key = hashlib.sha256(header.read_bytes() + source.read_bytes()).hexdigest()[:16]
    exe = work / f"peer_build_{key}"
    if not exe.exists():
        cmd = ["g++", "-O3", "-march=native", "-std=c++17", "-pthread", "-w",
               f"-I{header.parent}", str(source), "-o", str(exe)]
        subprocess.run(cmd, check=True)
    return exe


def run_peer(exe: Path, files: tuple[Path, Path], builder: str, threads: int,
             repeat: int) -> tuple[float, float]:
    """One tinybvh process on the first `threads` cores: (median ms after its warm-up, SAH)."""
    cores = ",".join(str(c) for c in sorted(os.sched_getaffinity(0))[:threads])
    out = subprocess.run(["taskset", "-c", cores, str(exe), *map(str, files), builder,
                          str(int(threads > 1)), str(repeat + 1)],
                         check=True, capture_output=True, text=True).stdout
    row = json.loads(out)
    return statistics.median(row["ms"][1:]), row["sah"]


def compare(v: np.ndarray, f: np.ndarray, files: tuple[Path, Path], threads: int,
            rounds: int, repeat: int, exe: Path) -> dict:
    """One size on `threads` cores: ours and the peers in alternating order each round."""
    from scenesort import kernels

    kernels.build_bvh(v, f[:WARM_UP], workers=threads)  # compile, off the clock
    times: dict[str, list[float]] = {"ours": [], **{p: [] for p in PEERS}}
    sah: dict[str, float] = {}

    def ours() -> None:
        stats = [kernels.build_bvh(v, f, workers=threads).stats for _ in range(repeat + 1)]
        times["ours"].append(statistics.median(s.build_ms for s in stats[1:]))
        sah["ours"] = stats[-1].sah_cost

    def peer(name: str) -> None:
        ms, sah[name] = run_peer(exe, files, name, threads, repeat)
        times[name].append(ms)

    steps = [ours, *(lambda p=p: peer(p) for p in PEERS)]
    for r in range(rounds):
        for step in steps if r % 2 == 0 else steps[::-1]:
            step()
    med = {k: statistics.median(x) for k, x in times.items()}
    return {"triangles": len(f), "threads": threads, "ms": med, "rounds": times, "sah": sah,
            "mtris": {k: len(f) / m / 1e3 for k, m in med.items()}}


def measure(size: int, thread_counts: list[int], rounds: int, repeat: int, exe: Path,
            work: Path) -> list[dict]:
    """The gallery of `size` triangles, written for the peer, at each thread count."""
    v, f, _ = gallery(size, STATUES)
    v4 = np.zeros((len(v), 4), np.float32)
    v4[:, :3] = v
    files = (work / f"v{size}.bin", work / f"f{size}.bin")
    v4.tofile(files[0])
    np.ascontiguousarray(f, dtype=np.uint32).tofile(files[1])
    rows = []
    for threads in thread_counts:
        r = compare(v, f, files, threads, rounds, repeat, exe)
        rows.append(r)
        med, mt, sah = r["ms"], r["mtris"], r["sah"]
        print(f"{len(f):>11,} {threads} | ours {med['ours']:7.0f} ms {mt['ours']:5.2f} "
              f"Mtris/s SAH {sah['ours']:.2f} | "
              + " | ".join(f"{p} {med[p]:7.0f} ms {mt[p]:5.2f} SAH {sah[p]:.2f}"
                           for p in PEERS), flush=True)
    return rows


def table(rows: list[dict]) -> str:
    head = ("| triangles | threads | ours ms | ours Mtris/s | "
            + " | ".join(f"{PEER_NAMES[p]} ms | Mtris/s | ours / it" for p in PEERS)
            + " | SAH cost: ours, BuildAVX |\n|---|---|---|---|"
            + "---|---|---|" * len(PEERS) + "---|\n")
    lines = []
    for r in rows:
        ms, mt = r["ms"], r["mtris"]
        lines.append(f"| {r['triangles']:,} | {r['threads']} | {ms['ours']:.0f} | "
                     f"{mt['ours']:.2f} | "
                     + " | ".join(f"{ms[p]:.0f} | {mt[p]:.2f} | {mt['ours'] / mt[p]:.2f}x"
                                  for p in PEERS)
                     + f" | {r['sah']['ours']:.2f}, {r['sah']['avx']:.2f} |")
    return head + "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tinybvh", type=Path, required=True,
                        help="tiny_bvh.h of a clone of https://github.com/jbikker/tinybvh")
    parser.add_argument("--sizes", default="1000000,4000000")
    parser.add_argument("--threads", default="1,2")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--no-docs", action="store_true", help="print only")
    args = parser.parse_args(argv)
    if not args.tinybvh.is_file():
        parser.error(f"--tinybvh {args.tinybvh}: no such file; pass the tiny_bvh.h of a "
                     "clone of https://github.com/jbikker/tinybvh")
    import warp as wp

    wp.config.quiet = True
    threads = [int(t) for t in args.threads.split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        exe = compile_harness(args.tinybvh.resolve(), work)
        rows = [row for size in args.sizes.split(",")
                for row in measure(int(size), threads, args.rounds, args.repeat, exe, work)]
    text = table(rows)
    print(text)
    if not args.no_docs:
        FIGURES.mkdir(parents=True, exist_ok=True)
        (FIGURES / "peer_build.json").write_text(json.dumps(
            {"machine": platform.processor() or platform.machine(), "cores": os.cpu_count(),
             "rows": rows}, indent=1))
        command = ("python benchmarks/peer_build.py --tinybvh <clone>/tiny_bvh.h "
                   + " ".join(a for a in (argv if argv is not None else sys.argv[1:])
                              if not a.startswith("--tinybvh") and a != str(args.tinybvh)))
        write_section("peer-build", f"Run: `{command.strip()}` ({os.cpu_count()} cores; "
                      f"medians of {args.rounds} interleaved rounds, each the median of "
                      f"{args.repeat} builds after a warm-up).\n\n{text}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
