"""The CUDA section of docs/benchmarks.md from `benchmarks/gpu_tables.py --json` files,
beside the papers' own GTX 580 figures (benchmarks/paper_figures.py).

    python benchmarks/gpu_report.py NEWEST.json [OLDER.json ...] [--check GPU_CHECK.log]
        [--tests "356 passed in 41 s"] [--no-docs]

Each table comes from the newest run that measured its part (the runs are listed with what
each one measured). `--check` adds the table `benchmarks/gpu_check.py` printed (device
against CPU, every result checked) and `--tests` its test summary. Prints the section and,
unless --no-docs, writes it between the `gpu` markers of docs/benchmarks.md. Needs no GPU:
the figures are the ones the files hold.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import paper_figures as paper  # noqa: E402
from docs_section import write_section  # noqa: E402

KINDS = ("primary", "ao", "random")
NOT_MEASURED = ("Not measured yet: the runs' time budget ended before this part (the "
                "device-against-CPU table above and the sweeps below have 1024^2 and 512^2 "
                "rows of it). `python benchmarks/gpu_tables.py --parts dacrt --dacrt-scenes "
                "conference,sponza --repeat 2 --budget 900 --json dacrt.json` measures it, "
                "about 15 minutes of an H200 at the task-pool DACRT's current speed.")


def fmt(x, digits: int = 3) -> str:
    if x is None:
        return "-"
    if isinstance(x, float):
        return f"{x:,.0f}" if abs(x) >= 1000 else f"{x:.{digits}g}"
    return f"{x:,}" if isinstance(x, int) else str(x)


def table(head: list[str], body: list[list]) -> str:
    if not body:
        return "(not measured in this run)"
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(fmt(c) for c in row) + " |" for row in body]
    return "\n".join(lines)


def rows_of(data: dict, part: str) -> list[dict]:
    return [r for r in data["rows"] if r["part"] == part and "error" not in r]


def merge(runs: list[dict]) -> dict:
    """One run's worth of rows: each part from the first run (newest) that has it, tagged
    with that run's number (runs counted from the oldest)."""
    rows = []
    for part in ("trace", "build", "dacrt", "sweep"):
        for k, run in enumerate(runs):
            got = rows_of(run, part)
            if got:
                rows += [{**r, "run": len(runs) - k} for r in got]
                break
    return {"device": runs[0]["device"], "rows": rows}


def run_of(data: dict, part: str) -> str:
    runs = sorted({r["run"] for r in data["rows"] if r["part"] == part})
    return f"run {runs[0]}" if runs else "not measured"


def runs_section(runs: list[dict]) -> str:
    body = []
    for k, run in reversed(list(enumerate(runs))):
        meta = run.get("meta", {})
        parts = sorted({r["part"] for r in run["rows"] if "error" not in r})
        body.append([len(runs) - k, meta.get("date"), ", ".join(parts),
                     f"`{' '.join(a for a in meta.get('argv', []) if '/' not in a)}`",
                     meta.get("note", "")])
    return table(["run", "date", "parts measured", "arguments", "code"], body)


def trace_section(data: dict) -> str:
    rows = rows_of(data, "trace")
    body = []
    for scene in dict.fromkeys(r["scene"] for r in rows):
        for kind in KINDS:
            get = {r["who"]: r for r in rows if r["scene"] == scene and r["kind"] == kind}
            ours = get.get("ours w2")
            if ours is None:
                continue
            mesh = [get[w]["mrays_s"] for w in ("wp.Mesh sah", "wp.Mesh lbvh") if w in get]
            ref = paper.BVH_SAH.get(scene)
            p = ref[2 + KINDS.index(kind)][0] if ref else None
            check = f"{ours['hitmiss']} / {ours.get('tri_diff', '-')}"
            body.append([scene, kind, ours["rays"], ours["mrays_s"],
                          get.get("wp.Mesh sah", {}).get("mrays_s"),
                          get.get("wp.Mesh lbvh", {}).get("mrays_s"),
                          ours["mrays_s"] / max(mesh) if mesh else None, p,
                          ours["mrays_s"] / p if p else None, check])
    return table(["scene", "kind", "rays", "ours MRays/s", "wp.Mesh sah", "wp.Mesh lbvh",
                  "ours / best wp.Mesh", "paper (SAH, leaf 8)", "ours / paper",
                  "vs CPU: hit/miss / triangle differences"], body)


def build_section(data: dict) -> str:
    rows = rows_of(data, "build")
    body = []
    for scene in dict.fromkeys(r["scene"] for r in rows):
        get = {(r["who"], r["method"], r["leaf"]): r for r in rows if r["scene"] == scene}
        tris = next(r["tris"] for r in rows if r["scene"] == scene)
        ours = [get.get(("ours", m, leaf), {}).get("wall_ms") for m in ("median", "sah")
                for leaf in paper.LEAVES]
        sah8 = get.get(("ours", "sah", 8), {})
        ref = paper.BVH_SAH.get(scene)
        body.append([scene, tris, *ours, sah8.get("pool_ms"),
                     get.get(("wp.Mesh sah", "sah", None), {}).get("wall_ms"),
                     get.get(("wp.Mesh lbvh", "lbvh", None), {}).get("wall_ms"),
                     ref[1][0] if ref else None,
                     ref[1][0] / sah8["wall_ms"] if ref and sah8 else None])
    return table(["scene", "triangles", "median 8", "median 16", "median 32", "SAH 8",
                  "SAH 16", "SAH 32", "SAH 8: pool launch", "wp.Mesh sah", "wp.Mesh lbvh",
                  "paper SAH 8", "paper / ours (SAH 8)"], body)


def dacrt_section(data: dict) -> tuple[str, str]:
    rows = rows_of(data, "dacrt")
    pool, bf = [], []
    for scene in dict.fromkeys(r["scene"] for r in rows):
        for split in ("median", "rdh"):
            for size in sorted({r["size"] for r in rows if r["method"] == split}):
                get = {r["kind"]: r for r in rows if r["scene"] == scene
                       and r["method"] == split and r["size"] == size}
                if not get:
                    continue
                ref = paper.DACRT_POOL.get(scene, {})
                cells = []
                for kind in KINDS:
                    ours = get.get(kind, {}).get("mrays_s")
                    p = ref.get((split, kind, size))
                    cells += [ours, p, ours / p if ours and p else None]
                miss = sum(r["hitmiss_vs_bvh"] for r in get.values())
                pool.append([scene, split, size, *cells, miss])
        get = {r["kind"]: r for r in rows if r["scene"] == scene and r["method"] == "bf"}
        if get:
            ref = paper.BREADTH_FIRST_MS.get(scene, {})
            cells = []
            for kind in ("primary", "shadow", "specular", "ao"):
                ours = get.get(kind, {}).get("trace_ms")
                p = ref.get(kind)
                cells += [ours, p, p / ours if ours and p else None]
            peak = get.get("primary", {}).get("peak_mb")
            bf.append([scene, *cells, peak, paper.BREADTH_FIRST_PEAK_MB.get(scene),
                       sum(r["hitmiss_vs_bvh"] for r in get.values())])
    pool_head = ["scene", "split", "size"]
    for kind in KINDS:
        pool_head += [f"{kind} MRays/s", "paper", "ours / paper"]
    bf_head = ["scene"]
    for kind in ("primary", "shadow", "specular", "AO"):
        bf_head += [f"{kind} ms", "paper", "paper / ours"]
    return (table(pool_head + ["hit/miss vs BVH"], pool),
            table(bf_head + ["peak MB (primary)", "paper peak MB", "hit/miss vs BVH"], bf))


def sweep_section(data: dict) -> str:
    rows = rows_of(data, "sweep")
    out = []
    build = [r for r in rows if r["what"].startswith("build")]
    if build:
        out.append(table(["scene", "workers", "K", "build ms", "pool launch ms", "nodes"],
                         [[r["scene"], r["workers"], r["k"], r["wall_ms"], r["pool_ms"],
                           r.get("nodes")] for r in build]))
    dacrt = [r for r in rows if r["what"].startswith("dacrt")]
    if dacrt:
        out.append(table(["what", "rays", "workers", "trace ms", "hit/miss vs BVH"],
                         [[r["what"], r["scene"], r.get("workers"), r["trace_ms"],
                           r.get("hitmiss_vs_bvh")] for r in dacrt]))
    block = [r for r in rows if "block_dim" in r]
    if block:
        out.append(table(["block_dim", "primary ms", "MRays/s"],
                         [[r["block_dim"], r["ms"], r["mrays_s"]] for r in block]))
    return "\n\n".join(out)


def section(runs: list[dict], check: str | None, tests: str | None) -> str:
    data = merge(runs)
    meta = runs[0].get("meta", {})
    pool, bf = dacrt_section(data)
    parts = [
        f"## CUDA: the papers' GPU tables on an {data['device']}",
        f"Produced by `benchmarks/gpu_tables.py` on one {data['device']} "
        f"({meta.get('sms')} SMs, driver {meta.get('driver')}, Warp {meta.get('warp')} built "
        f"with CUDA {meta.get('toolkit')}), rendered by `benchmarks/gpu_report.py` from the "
        "runs below (raw rows in docs/figures/gpu/). Device rows are medians of "
        f"{meta.get('repeat')} runs after a warm-up (sweeps: of 2), compilation excluded. The "
        "papers' figures are theirs, on a GTX 580 (benchmarks/paper_figures.py); their "
        "Dragon, Buddha and Blade are the full scans, 9-11x the triangles of the shared ones.",
        runs_section(runs),
        *([f"Device tests (`pytest tests/kernels tests/stability -k cuda`): {tests}."]
          if tests else []),
        *(["### Device against CPU (`benchmarks/gpu_check.py`, 1024x1024 camera rays, "
           "numpy in and out: transfers and validation counted)", f"```\n{check}\n```"]
          if check else []),
        f"### Trace (2012 paper, Tables 6.1/6.2; {run_of(data, 'trace')}): MRays/s of the "
        "kernel, rays and hits on the device",
        trace_section(data),
        f"### Build (Tables 6.1/6.2; {run_of(data, 'build')}): ms of `build_bvh` from numpy "
        "(upload included), spatial median and binned SAH at leaf sizes 8/16/32",
        build_section(data),
        f"### Task-pool DACRT (Table 6.3, the papers' constants; {run_of(data, 'dacrt')}): "
        "MRays/s",
        pool if "not measured" not in pool else NOT_MEASURED,
        "### Breadth-first DACRT (2013 paper, Tables 1-3, alpha = beta = 256; "
        f"{run_of(data, 'dacrt')}): ms per frame",
        bf if "not measured" not in bf else NOT_MEASURED,
        f"### Sweeps ({run_of(data, 'sweep')}): persistent workers and K of the build (binned "
        "SAH, leaf 8), workers and C_SORT of the task-pool DACRT (RDH), alpha and beta of the "
        "breadth-first DACRT, block size of the trace kernel",
        sweep_section(data),
    ]
    return "\n\n".join(p for p in parts if p)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("json", nargs="+", help="gpu_tables.py --json files, newest first")
    p.add_argument("--check", default=None, help="a gpu_check.py log")
    p.add_argument("--tests", default=None, help="the device tests' summary line")
    p.add_argument("--no-docs", action="store_true")
    args = p.parse_args()
    runs = [json.loads(Path(f).read_text()) for f in args.json]
    check = None
    if args.check:
        lines = Path(args.check).read_text().splitlines()
        start = next(i for i, ln in enumerate(lines) if ln.startswith("scene "))
        check = "\n".join(lines[start - 1:])
    body = section(runs, check, args.tests)
    print(body)
    if not args.no_docs:
        write_section("gpu", body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
