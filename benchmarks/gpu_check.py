"""The engine on a CUDA GPU: its device tests, then a short benchmark beside the CPU.

    .venv/bin/python benchmarks/gpu_check.py [--scenes bunny,sponza] [--size 1024]
        [--repeat 3] [--no-tests] [--test-workers 8] [--junit F] [--device cuda:0]

On a machine with a CUDA device it
1. runs the device tests: `pytest tests/kernels tests/stability -k cuda` (every engine test
   is parametrised over the devices present, tests/devices.py; the CUDA compile test apart),
   in --test-workers processes with pytest-xdist where it is installed, and prints their
   summary;
2. times, on two shared scenes (an object and an indoor scene) at size x size camera rays:
   BVH build (binned SAH), closest-hit trace, any-hit trace (one occlusion ray per primary
   hit, within 0.1 of the scene box's diagonal), task-pool DACRT (RDH) and breadth-first
   DACRT of the primary rays, and AO (4 samples per pixel) - on the device and on the CPU,
   each result checked against the CPU's (hit/miss mismatches, AO max difference);
3. prints one table: device ms, CPU ms (every core), CPU / device.
The device rows are the median of --repeat runs after a warm-up (compile excluded); the
CPU rows one run after a warm-up, to stay within about four minutes in all.

Without a CUDA device it says so and exits 0: the CUDA path is then only compiled, by
tests/kernels/test_cuda_compile.py in CI. `--device cpu` runs the same program against the
CPU itself (to check the program, not the GPU).
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import warp as wp  # noqa: E402

wp.config.quiet = True

from scenesort.backend.render.scenes import shared_scene  # noqa: E402

from scenesort import kernels  # noqa: E402

AO_SPP = 4


def run_device_tests(device: str, workers: int, junit: str | None) -> str:
    """The device half of the engine's tests (the CUDA compile test apart: it needs no GPU);
    returns pytest's summary line. With pytest-xdist, `workers` processes share the GPU, and
    a test that hangs is ended by its timeout without ending the others."""
    kind = device.split(":")[0]
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-rfE",
           "--timeout=120", "tests/kernels", "tests/stability",
           "-k", f"{kind} and not test_cuda_compile"]
    if workers > 1 and importlib.util.find_spec("xdist") is not None:
        cmd += ["-n", str(workers), "--timeout-method=thread"]
    if junit:
        cmd += [f"--junitxml={junit}"]
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    lines = [ln for ln in proc.stdout.splitlines() if ln.strip()]
    if proc.returncode != 0:
        print("\n".join(lines[-60:]))
    return lines[-1] if lines else f"pytest exited {proc.returncode}"


def timed(fn, repeat: int) -> tuple[float, object]:
    """(median ms of `repeat` calls after one warm-up, the last result)."""
    out = fn()
    samples = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        wp.synchronize()
        samples.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(samples), out


def mismatches(a, b) -> int:
    return int(np.count_nonzero((a.triangle >= 0) != (b.triangle >= 0)))


def scene_rows(name: str, size: int, device: str, repeat: int, deadline: float) -> list[tuple]:
    scene = shared_scene(name)
    v, f = scene.vertices, scene.indices
    o, d, tmin, tmax = replace(scene.camera, width=size, height=size).rays()
    rows = []

    def row(what: str, rays: int, dev_fn, cpu_fn, check) -> None:
        if time.perf_counter() > deadline:
            rows.append((name, what, rays, None, None, "skipped: time budget"))
            return
        dev_ms, dev_out = timed(dev_fn, repeat)
        cpu_ms, cpu_out = timed(cpu_fn, 1)
        rows.append((name, what, rays, dev_ms, cpu_ms, check(dev_out, cpu_out)))

    bvhs = {}

    def build(dev: str):
        bvhs[dev] = kernels.build_bvh(v, f, device=dev)
        return bvhs[dev]

    row("BVH build (SAH)", 0, lambda: build(device), lambda: build("cpu"),
        lambda a, b: f"nodes {a.stats.nodes:,} / {b.stats.nodes:,}")
    if device not in bvhs or "cpu" not in bvhs:
        return rows
    ref = kernels.trace(bvhs["cpu"], o, d, tmin, tmax)
    row("trace, closest hit", len(o), lambda: kernels.trace(bvhs[device], o, d, tmin, tmax),
        lambda: kernels.trace(bvhs["cpu"], o, d, tmin, tmax),
        lambda a, b: f"{mismatches(a, b)} mismatches")
    hit = ref.triangle >= 0
    rng = np.random.default_rng(0)
    w = rng.normal(size=(int(hit.sum()), 3)).astype(np.float32)
    diag = float(np.linalg.norm(bvhs["cpu"].bounds[1] - bvhs["cpu"].bounds[0]))
    p = (o[hit] + ref.t[hit, None] * d[hit]).astype(np.float32)
    w *= np.sign(np.einsum("ij,ij->i", w, -d[hit]))[:, None]  # back toward the camera side
    so = (p + 1e-4 * diag * w / np.linalg.norm(w, axis=1, keepdims=True)).astype(np.float32)
    row("trace, any hit", len(so),
        lambda: kernels.trace(bvhs[device], so, w, 0.0, 0.1 * diag, any_hit=True),
        lambda: kernels.trace(bvhs["cpu"], so, w, 0.0, 0.1 * diag, any_hit=True),
        lambda a, b: f"{mismatches(a, b)} mismatches")
    for variant in ("pool", "breadth_first"):
        row(f"DACRT {variant.replace('_', '-')}", len(o),
            lambda variant=variant: kernels.dacrt_trace(v, f, o, d, tmin, tmax, variant=variant,
                                                        device=device),
            lambda variant=variant: kernels.dacrt_trace(v, f, o, d, tmin, tmax, variant=variant,
                                                        device="cpu"),
            lambda a, b: f"{mismatches(a, ref)} / {mismatches(b, ref)} mismatches vs BVH")
    row(f"AO, {AO_SPP} spp", len(o),
        lambda: kernels.render_ao(bvhs[device], o, d, spp=AO_SPP, tmin=tmin, tmax=tmax).ao,
        lambda: kernels.render_ao(bvhs["cpu"], o, d, spp=AO_SPP, tmin=tmin, tmax=tmax).ao,
        lambda a, b: f"max |diff| {float(np.abs(a - b).max()):.2g}")
    return rows


def print_table(rows: list[tuple], device: str, cores: int) -> None:
    head = ("scene", "what", "rays", f"{device} ms", f"CPU ms ({cores} cores)", "CPU/device",
            "check")
    body = []
    for name, what, rays, dev_ms, cpu_ms, check in rows:
        if dev_ms is None:
            body.append((name, what, f"{rays:,}" if rays else "", "", "", "", check))
            continue
        body.append((name, what, f"{rays:,}" if rays else "", f"{dev_ms:.1f}", f"{cpu_ms:.1f}",
                     f"{cpu_ms / dev_ms:.2f}", check))
    widths = [max(len(str(r[i])) for r in [head, *body]) for i in range(len(head))]
    for r in [head, tuple("-" * w for w in widths), *body]:
        print(" | ".join(str(c).ljust(w) for c, w in zip(r, widths, strict=True)))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", default="bunny,sponza")
    p.add_argument("--size", type=int, default=1024)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--device", default="cuda:0")
    p.add_argument("--no-tests", action="store_true")
    p.add_argument("--budget", type=float, default=225.0,
                   help="seconds from the start after which no timing row is added")
    p.add_argument("--test-workers", type=int, default=8,
                   help="pytest-xdist processes sharing the device (when xdist is installed)")
    p.add_argument("--junit", default=None, help="write the device tests' JUnit XML here")
    args = p.parse_args()
    start = time.perf_counter()
    wp.init()
    if args.device != "cpu" and not wp.is_cuda_available():
        print("no CUDA device here: nothing to run. The CUDA path is compiled (sm_80, sm_90) "
              "by tests/kernels/test_cuda_compile.py; run this program on a machine with a GPU.")
        return 0
    device = str(wp.get_device(args.device))
    print(f"device {device}: {wp.get_device(args.device).name}")
    if not args.no_tests:
        summary = run_device_tests(device, args.test_workers, args.junit)
        print(f"device tests: {summary} ({time.perf_counter() - start:.0f} s)", flush=True)
    deadline = start + args.budget
    rows = []
    for name in args.scenes.split(","):
        rows += scene_rows(name, args.size, device, args.repeat, deadline)
    from scenesort.kernels.core import cpu_cores

    print(f"{args.size}x{args.size} camera rays; {device}: median of {args.repeat} after a "
          f"warm-up; CPU: one run after a warm-up; {time.perf_counter() - start:.0f} s in all")
    print_table(rows, device, cpu_cores())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
