"""Numerical stability, case by case, for scenesort's BVH and its peers on the same inputs
in the same run: Embree (embreex, default flags) and Warp's own `wp.Mesh` (`mesh_query_ray`).

    .venv/bin/python benchmarks/stability.py [--quick] [--out docs/robustness.md]

Per case: rays tried, failures (escapes from closed meshes, hit/miss flips away from
rounding ties, farther-than-closest hits, hits outside the triangle: the float64 oracle of
tests/stability/cases.py judges) and the largest relative t error against the float64
distance to the hit triangle's plane. The peers are judged on hits alone (neither refines
t); scenesort also must keep t within 2 float32 ulps, and a t beyond that is a failure.
`--quick` runs a small sweep (about a minute); the full run adds the 2-million-triangle
and 10-million-ray cases and larger meshes. Writes the table between the `stability` markers
of `--out` (the rest of that doc is by hand) and the figures as JSON into `--json`
(docs/figures/stability.json).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from docs_section import write_section  # noqa: E402  (benchmarks/ is on sys.path)

from scenesort import kernels  # noqa: E402
from tests.stability import cases as C  # noqa: E402
from tests.stability.test_axis_aligned import in_wall_rays, room  # noqa: E402

wp.config.quiet = True


# --- the peers ---------------------------------------------------------------------------


def embree_trace(v, f, o, d):
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene, v, f)
    res = scene.run(o, d, output=1)
    tri = res["primID"].astype(np.int64)
    return np.where(tri >= 0, res["tfar"], np.inf).astype(np.float32), tri


@wp.kernel
def _mesh_rays(mesh: wp.uint64, o: wp.array(dtype=wp.vec3), d: wp.array(dtype=wp.vec3),
               out_t: wp.array(dtype=float), out_face: wp.array(dtype=int)):
    i = wp.tid()
    q = wp.mesh_query_ray(mesh, o[i], d[i], 1.0e30)
    out_t[i] = wp.inf
    out_face[i] = -1
    if q.result:
        out_t[i] = q.t
        out_face[i] = q.face


def warp_mesh_trace(v, f, o, d):
    mesh = wp.Mesh(points=wp.array(v, dtype=wp.vec3), indices=wp.array(f.ravel(), dtype=int))
    n = len(o)
    t = wp.empty(n, dtype=float)
    face = wp.empty(n, dtype=int)
    if n:
        wp.launch(_mesh_rays, dim=n, inputs=[mesh.id, wp.array(o, dtype=wp.vec3),
                                             wp.array(d, dtype=wp.vec3), t, face])
    return t.numpy(), face.numpy().astype(np.int64)


def ours_trace(v, f, o, d):
    h = kernels.trace(kernels.build_bvh(v, f), o, d)
    return h.t, h.triangle


TRACERS = {"scenesort": ours_trace, "embree": embree_trace, "wp.Mesh": warp_mesh_trace}


# --- cases: each yields (name, v, f, o, d, judge) with judge "escape" or "closest" ---------


def watertight_cases(quick: bool):
    sweep = [(1.0, 0.0), (1e-4, 0.0), (1e4, 0.0), (1e-2, 1e2), (1.0, 1e4), (1e3, 1e5),
             (10.0, 1e6)]
    if quick:
        sweep = [(1.0, 0.0), (1e-4, 0.0), (1.0, 1e4), (10.0, 1e6)]
    for name in sorted(C.CLOSED_MESHES):
        for scale, offset in sweep:
            v, f, o, d = C.watertight_case(name, scale, offset)
            yield f"watertight {name} s={scale:g} off={offset:g}", v, f, o, d, "escape"
    if not quick:  # a finer sphere: 5120 triangles, 4 x 10242 + 4 x 15360 targets
        C.CLOSED_MESHES["icosphere5"] = lambda: C.icosphere(5)
        for scale, offset in sweep:
            v, f, o, d = C.watertight_case("icosphere5", scale, offset)
            yield f"watertight icosphere(5) s={scale:g} off={offset:g}", v, f, o, d, "escape"


def sweep_cases(quick: bool):
    sweep = [(1.0, 0.0), (1e-4, 0.0), (1e4, 0.0), (1e-2, 1e2), (1.0, 1e4), (1e3, 1e5),
             (10.0, 1e6)]
    rays = 1500 if quick else 6000
    for scale, offset in (sweep[::2] if quick else sweep):
        v, f = C.mixed_scene(0, scale, offset)
        o, d = C.scene_rays(v, f, rays, seed=1)
        yield f"scale/offset mixed scene s={scale:g} off={offset:g}", v, f, o, d, "closest"


def axis_cases(quick: bool):
    for scale, offset in [(1.0, 0.0), (1e3, 1e5)]:
        v, f = room(scale, offset)
        for neg in (False, True):
            o, d = in_wall_rays(v, neg)
            sign = "-0" if neg else "+0"
            yield (f"axis-aligned in-wall rays ({sign}) s={scale:g} off={offset:g}", v, f, o,
                   d, "escape")
    v, f = C.plane_grid(4)
    rng = np.random.default_rng(8)
    n = 2000 if quick else 20000
    angle = np.exp(rng.uniform(np.log(1e-7), np.log(1e-2), n))
    az = rng.uniform(0, 2 * np.pi, n)
    d = np.stack([np.cos(az) * np.cos(angle), -np.sin(angle), np.sin(az) * np.cos(angle)], 1)
    o = np.stack([rng.uniform(-1, 1, n), rng.uniform(0, 1e-3, n), rng.uniform(-1, 1, n)], 1)
    yield "grazing rays 1e-7..1e-2 rad", v, f, o.astype(np.float32), d.astype(np.float32), \
        "closest"


def degenerate_cases(quick: bool):
    v, f = C.mixed_scene(2)
    bad = f[::10].copy()
    bad[:, 2] = bad[:, 1]
    f2 = np.vstack([f, bad])
    o, d = C.scene_rays(v, f, 1500 if quick else 6000, seed=3)
    yield "degenerate copies mixed in", v, f2, o, d, "closest"
    yield "one huge + 3000 tiny triangles", *C.huge_over_tiny(3000), "closest"


def size_cases(quick: bool):
    if quick:
        return
    sv, sf = C.icosphere(8)
    rng = np.random.default_rng(1)
    soup = rng.uniform(-1, 1, (700_000, 1, 3)) * 50 + rng.normal(size=(700_000, 3, 3))
    soup = soup[np.linalg.norm(soup.mean(axis=1), axis=1) > 5].reshape(-1, 3)
    v = np.vstack([sv, soup]).astype(np.float32)
    f = np.vstack([sf, len(sv) + np.arange(len(soup)).reshape(-1, 3)]).astype(np.int32)
    o = rng.uniform(-0.5, 0.5, (1_000_000, 3)).astype(np.float32)
    d = rng.normal(size=(1_000_000, 3)).astype(np.float32)
    yield f"{len(f) / 1e6:.2f}M triangles, 1M rays from inside the sphere", v, f, o, d, "escape"
    v, f = C.box_room(4)
    n = 10_000_000
    o = (rng.uniform(-0.9, 0.9, (n, 3)) * [1, 0.5, 0.7]).astype(np.float32)
    d = rng.normal(size=(n, 3)).astype(np.float32)
    yield "10M rays inside a closed room", v.astype(np.float32), f, o, d, "escape"


def judge(kind, v, f, o, d, t, tri, exact_t):
    if kind == "escape":
        return C.check_escapes(v, f, o, d, t, tri, exact_t=exact_t)
    return C.check_closest(v, f, o, d, t, tri, exact_t=exact_t)


def run_case(name, v, f, o, d, kind) -> dict:
    row = {"case": name, "triangles": int(len(f)), "rays": int(len(o)), "judge": kind}
    for tracer, fn in TRACERS.items():
        t0 = time.perf_counter()
        t, tri = fn(v, f, o, d)
        seconds = time.perf_counter() - t0
        check = judge(kind, v, f, o, d, t, tri, exact_t=tracer == "scenesort")
        row[tracer] = {"failures": check.failures, "max_t_err": check.max_t_err,
                       "kinds": check.kinds, "seconds": round(seconds, 3)}
    return row


def graceful_rows() -> list[dict]:
    """Beyond float32's range of products: a triangle of size 1e-30 or 1e30 (edge
    functions under/overflow float32). Counted: rays that should hit its interior."""
    rows = []
    for scale in (1e-30, 1e-20, 1e20, 1e30):
        v = (np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]]) * scale).astype(np.float32)
        f = np.array([[0, 1, 2]], np.int32)
        rng = np.random.default_rng(0)
        p = np.column_stack([rng.uniform(0.05, 0.45, 200), rng.uniform(0.05, 0.45, 200),
                             np.zeros(200)])
        o = ((p + [0, 0, 1]) * scale).astype(np.float32)
        d = np.tile(np.array([[0.0, 0.0, -1.0]]) * scale, (200, 1)).astype(np.float32)
        row = {"case": f"single triangle of size {scale:g} (graceful failure)",
               "triangles": 1, "rays": 200, "judge": "escape"}
        for tracer, fn in TRACERS.items():
            t, tri = fn(v, f, o, d)
            bad_t = np.isfinite(t) & (np.abs(t - 1.0) > 1e-6)
            row[tracer] = {"failures": int(np.sum(tri < 0) + np.sum(bad_t)),
                           "max_t_err": float(np.abs(t[tri >= 0] - 1).max(initial=0)),
                           "kinds": {"missed": int(np.sum(tri < 0)),
                                     "nan_t": int(np.isnan(t).sum())}, "seconds": 0.0}
        rows.append(row)
    return rows


def table(rows: list[dict]) -> str:
    head = ("| case | triangles | rays | scenesort failures | scenesort max t err | "
            "Embree failures | Embree max t err | wp.Mesh failures | wp.Mesh max t err |")
    lines = [head, "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        cells = [r["case"], f"{r['triangles']:,}", f"{r['rays']:,}"]
        for tracer in TRACERS:
            cells += [f"{r[tracer]['failures']:,}", f"{r[tracer]['max_t_err']:.2g}"]
        lines.append("| " + " | ".join(cells) + " |")
    real = [r for r in rows if "graceful" not in r["case"]]
    tot = {k: sum(r[k]["failures"] for r in real) for k in TRACERS}
    lines.append(f"| **total (without graceful rows)** | | {sum(r['rays'] for r in real):,} "
                 f"| **{tot['scenesort']:,}** "
                 f"| | **{tot['embree']:,}** | | **{tot['wp.Mesh']:,}** | |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small sweep (about a minute)")
    ap.add_argument("--out", default=str(REPO / "docs" / "robustness.md"))
    ap.add_argument("--json", default=str(REPO / "docs" / "figures" / "stability.json"))
    args = ap.parse_args()
    wp.init()
    rows = []
    groups = [watertight_cases, sweep_cases, axis_cases, degenerate_cases, size_cases]
    t_start = time.perf_counter()
    for group in groups:
        for name, v, f, o, d, kind in group(args.quick):
            row = run_case(name, v, f, o, d, kind)
            rows.append(row)
            print(f"{name}: rays {row['rays']:,}  " + "  ".join(
                f"{k} {row[k]['failures']} ({row[k]['max_t_err']:.2g})" for k in TRACERS),
                flush=True)
    rows += graceful_rows()
    command = ".venv/bin/python benchmarks/stability.py" + (" --quick" if args.quick else "")
    meta = {"command": command, "quick": args.quick, "warp": wp.config.version,
            "python": platform.python_version(), "machine": platform.machine(),
            "seconds": round(time.perf_counter() - t_start, 1)}
    out_json = Path(args.json)
    out_json.parent.mkdir(parents=True, exist_ok=True)
    out_json.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    text = table(rows)
    print(text)
    write_doc(Path(args.out), text, meta, rows)


def write_doc(path: Path, text: str, meta: dict, rows: list[dict]) -> None:
    """The `stability` section of `path` (docs/robustness.md): how to read the table, the
    table, the failure kinds; the rest of that doc is written by hand."""
    kinds: dict[str, dict[str, int]] = {k: {} for k in TRACERS}
    for r in rows:
        for k in TRACERS:
            for kind, n in r[k]["kinds"].items():
                kinds[k][kind] = kinds[k].get(kind, 0) + n
    body = f"""## How to read the table

- Every reference quantity is float64 computed from the exact float32 inputs
  (`tests/stability/cases.py`). A ray that passes within 2^-14 of |vertex - origin| of a
  triangle's edge may be decided either way by any float32 tracer and is not counted.
- **failures** = rays that escaped a closed mesh, missed a triangle they clearly cross,
  returned a farther triangle than the closest one they clearly cross, or hit a triangle
  they clearly miss. For scenesort, a t more than 2 float32 ulps from the float64 plane
  distance also counts (it refines t in float64); the peers are judged on hits only.
- **max t err** = largest relative error of t against the float64 distance to the hit
  triangle's plane, over the hits.
- "watertight" rows: rays from 4-5 interior points aimed exactly at every vertex and
  every edge midpoint of a closed icosphere, box room (shared-vertex grid walls) and torus.
- Rows marked "graceful failure" are beyond float32: edge-function products under- or
  overflow. Nothing crashes and nothing returns NaN; these rays miss.

## Results

Command: `{meta['command']}` (warp {meta['warp']}, Python {meta['python']},
{meta['machine']}, CPU only, {meta['seconds']} s).

{text}

Failure kinds summed over all rows: scenesort {kinds['scenesort']}, Embree
{kinds['embree']}, wp.Mesh {kinds['wp.Mesh']}.

The full data, per case and failure kind, with timings, is in `docs/figures/stability.json`.
"""
    write_section("stability", body, path)


if __name__ == "__main__":
    main()
