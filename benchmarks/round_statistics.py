"""The adaptive controller's host work per round, the Warp kernels of
kernels/render/statistics.py against the numpy code they replaced
(tests/kernels/render/adaptive_reference.py, the tests' reference), in the same run.

    .venv/bin/python benchmarks/round_statistics.py [--sizes 160x120,512x384,3840x2160]
        [--repeat 5] [--no-docs]

A round's work outside the trace: the image's estimated error (`mse`), the next round's
allocation (`next_round`, target 0.02) and the bookkeeping of the round's samples (counts,
the sampler's spread sums), with a tracer that hands back counts made beforehand. Every hit
pixel is covered, with 16-128 samples as rounds leave them. Each repeat starts both from
the same counts after one untimed round (the kernels' arrays are made there, as in a
render's first round); the implementations alternate; medians. Both select the same pixels
(checked). Writes the round-statistics section of docs/benchmarks.md unless --no-docs.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks.docs_section import write_section  # noqa: E402

AIM = 0.82 * 0.02


def state(n: int, seed: int) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    done = rng.choice([16, 32, 64, 128], n, p=[0.4, 0.3, 0.2, 0.1]).astype(np.int64)
    p = np.where(rng.random(n) < 0.2, 1.0, rng.beta(2.0, 0.7, n))
    return done, rng.binomial(done, p).astype(np.int64), rng.binomial(done // 2, p)


def one_round(module, counts, traced: dict[int, tuple[np.ndarray, ...]]
              ) -> tuple[dict[str, float], np.ndarray]:
    """mse, next_round and the bookkeeping of one round (its groups by sample count as
    sample_rounds makes them); ms each; the selection."""
    times = {}
    start = time.perf_counter()
    counts.mse()
    times["mse"] = time.perf_counter()
    select = module.next_round(counts, AIM, None, 4096)
    times["next_round"] = time.perf_counter()
    levels = counts.done[select]
    for n in np.flatnonzero(np.bincount(levels)):
        group = select[levels == n]
        made = tuple(a[: len(group)] for a in traced[int(n)])
        counts.trace(lambda *_, made=made: made, group, int(n))
    times["bookkeeping"] = time.perf_counter()
    out, last = {}, start
    for phase, t in times.items():
        out[phase], last = (t - last) * 1e3, t
    out["total"] = (last - start) * 1e3
    return out, select


def measure(width: int, height: int, repeat: int) -> list[dict]:
    from scenesort.kernels.render import adaptive  # noqa: PLC0415

    from tests.kernels.render import adaptive_reference  # noqa: PLC0415

    n = width * height
    rng = np.random.default_rng(2)
    traced = {m: tuple(rng.binomial(m, 0.7, n).astype(np.int64) // d for d in (1, 2, 4))
              for m in (16, 32, 64, 128, 256)}
    kinds = {"numpy": (adaptive_reference, {}),
             "kernels, 1 thread": (adaptive, {"threads": 1}),
             f"kernels, {os.cpu_count()} threads": (adaptive, {})}
    runs: dict[str, list[dict]] = {k: [] for k in kinds}
    for r in range(repeat):
        selections = []
        for kind, (module, extra) in kinds.items():
            done, opened, before = state(n, r)
            counts = module.SampleCounts(done, opened, before,
                                         spread={16: 0.45, 32: 0.33, 64: 0.27},
                                         rho={32: 0.36, 64: 0.41}, **extra)
            one_round(module, counts, traced)  # untimed: the kernels' arrays made
            times, select = one_round(module, counts, traced)
            runs[kind].append(times)
            selections.append(select)
        assert all(np.array_equal(s, selections[0]) for s in selections)
    rows = []
    for kind, times in runs.items():
        med = {k: statistics.median(t[k] for t in times) for k in times[0]}
        rows.append({"size": f"{width}x{height}", "kind": kind, **med})
    base = rows[0]["total"]
    for row in rows:
        row["speed-up"] = base / row["total"]
        print(f"{row['size']:>10} {row['kind']:<20} mse {row['mse']:8.1f} next_round "
              f"{row['next_round']:8.1f} bookkeeping {row['bookkeeping']:8.1f} total "
              f"{row['total']:8.1f} ms  {row['speed-up']:5.2f}x", flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="160x120,512x384,3840x2160")
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--no-docs", action="store_true")
    args = parser.parse_args()
    load = os.getloadavg()
    rows = []
    for size in args.sizes.split(","):
        width, height = map(int, size.split("x"))
        rows += measure(width, height, args.repeat)
    if args.no_docs:
        return
    command = " ".join(["benchmarks/round_statistics.py", *sys.argv[1:]])
    lines = [
        "## The adaptive controller's host work per round (`benchmarks/round_statistics.py`)",
        "",
        f"Command: `.venv/bin/python {command}`; {os.cpu_count()} cores, load average "
        f"{' / '.join(f'{v:.2f}' for v in load)} before the run. One round outside the "
        "trace: the image's estimated error, the next round's allocation (target 0.02) and "
        "the round's bookkeeping, on counts of 16-128 samples; ms, medians of "
        f"{args.repeat} interleaved repeats; the numpy code is the one the kernels replaced "
        "(the tests' reference). Both select the same pixels.",
        "",
        "| image | implementation | mse | next_round | bookkeeping | total | speed-up |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for row in rows:
        lines.append(f"| {row['size']} | {row['kind']} | {row['mse']:.1f} | "
                     f"{row['next_round']:.1f} | {row['bookkeeping']:.1f} | "
                     f"{row['total']:.1f} | {row['speed-up']:.2f}x |")
    write_section("round_statistics", "\n".join(lines))


if __name__ == "__main__":
    main()
