"""`scenesort render-frames`: render a frame bundle (File > Export > scenesort animation).

    scenesort render-frames BUNDLE --out DIR [--frames 1-40,50] [--resume] [--threads N]
                            [--ray [ADDRESS|auto|local] [--ray-workers N] [--retries N]]

Writes `DIR/<frame>.png` (8-bit AO, the service's PNG) and `DIR/<frame>.npy` (float32 AO,
row 0 at the top) per frame with a progress bar, then a table of what the frames built:
meshes built, refit or reused, top levels built (render/bvhs.py's skip rules), and what
culling left out (instances out of view, meshes none of the instances in view uses).
With `--ray` the frames are Ray tasks on a cluster (render/cluster.py, docs/cluster.md).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from scenesort.backend.commands import ao_options, check_at_least


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bundle", type=Path, help="the bundle's folder (holds manifest.json)")
    parser.add_argument("--out", type=Path, required=True, help="folder for the frames")
    parser.add_argument("--frames", default=None,
                        help="which frames, e.g. 1-40,50 (default: all in the bundle)")
    parser.add_argument("--resume", action="store_true",
                        help="skip frames whose files are already in --out")
    parser.add_argument("--threads", type=int, default=None,
                        help="engine threads per frame (default: all cores; 1 with --ray)")
    parser.add_argument("--device", default="cpu", help="Warp device (default cpu)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    cluster = parser.add_argument_group("Ray cluster (pip install \"scenesort[cluster]\")")
    cluster.add_argument(
        "--ray", nargs="?", const="", default=None, metavar="ADDRESS",
        help="render the frames as Ray tasks: 'local' starts a cluster on this machine, "
             "'auto' joins the one `ray start` runs here, HOST:PORT or ray://HOST:10001 "
             "another; bare --ray is Ray's default (RAY_ADDRESS, else a local cluster)")
    cluster.add_argument("--ray-workers", type=int, default=None, metavar="N",
                         help="CPUs of the cluster --ray local starts (default: all cores)")
    cluster.add_argument("--retries", type=int, default=3, metavar="N",
                         help="times Ray retries a frame that fails (default 3)")
    cluster.add_argument("--gpus-per-frame", type=float, default=0.0, metavar="G",
                         help="GPUs each frame's task asks for; > 0 renders on CUDA")


def parse_frames(spec: str) -> list[int]:
    """'1-3,7' -> [1, 2, 3, 7]; ValueError naming --frames for anything else."""
    frames: list[int] = []
    for part in spec.split(","):
        first, dash, last = part.strip().partition("-")
        try:
            lo = int(first)
            hi = int(last) if dash else lo
        except ValueError:
            raise ValueError(f"--frames: {part!r} is not a frame or a range like 1-40") from None
        if hi < lo:
            raise ValueError(f"--frames: the range {part!r} ends before it starts")
        frames.extend(range(lo, hi + 1))
    return frames


def run(args: argparse.Namespace) -> int:
    from rich.console import Console
    from scenesort.backend.render.cluster import ClusterError

    console = Console()
    try:
        ao_options(args)  # --threads, as AoOptions takes it (the bundle holds the rest)
        check_at_least(args, 1, "ray_workers")
        check_at_least(args, 0, "retries")
        frames = None if args.frames is None else parse_frames(args.frames)
        start = time.perf_counter()
        if args.ray is None:
            from scenesort.backend.render.frames import render_frames

            done = render_frames(args.bundle, args.out, frames=frames, resume=args.resume,
                                 threads=args.threads, progress=not args.no_progress,
                                 device=args.device)
            failed: dict[int, str] = {}
        else:
            done, failed = _on_ray(args, frames, console)
    except (ValueError, ClusterError) as exc:  # BundleError names the file and the field;
        # ClusterError says what to install or start
        from rich.text import Text

        console.print(Text.assemble(("error:", "red"), f" {exc}"), soft_wrap=True)
        return 2
    console.print(_table(done, time.perf_counter() - start))
    console.print(f"wrote {sum(r is not None for _, r in done)} frames to {args.out}")
    if failed:
        for number, message in failed.items():
            console.print(f"frame {number} failed: {message}", markup=False, soft_wrap=True)
        console.print(f"{len(failed)} frames failed: {', '.join(map(str, failed))}; "
                      "rerun with --resume to render only those", soft_wrap=True)
        return 1
    return 0


def _on_ray(args: argparse.Namespace, frames: list[int] | None,
            console: Any) -> tuple[list[tuple[int, Any]], dict[int, str]]:
    from scenesort.backend.render.bundle import read_bundle
    from scenesort.backend.render.cluster import import_ray, render_frames_ray
    from scenesort.backend.render.frames import frame_progress

    import_ray()  # the missing extra, named before any work
    total = len(read_bundle(args.bundle).frames) if frames is None else len(frames)
    with frame_progress(total, not args.no_progress) as advance:
        run = render_frames_ray(
            args.bundle, args.out, address=args.ray or None, frames=frames,
            resume=args.resume, threads=args.threads or 1, workers=args.ray_workers,
            retries=args.retries, gpus=args.gpus_per_frame,
            on_frame=advance)
    console.print(f"Ray: cluster start-up {run.startup_s:.1f} s (apart), frames "
                  f"{run.render_s:.1f} s", markup=False)
    done = [(n, None) for n in run.skipped] + [(n, run.builds[n]) for n in run.written]
    return done, run.failed


def _table(done: list[tuple[int, Any]], seconds: float) -> Any:
    from rich.table import Table

    reports = [r for _, r in done if r is not None]
    table = Table(title=f"{len(reports)} frames rendered ({len(done) - len(reports)} "
                  f"skipped) in {seconds:.1f} s")
    for column in ("meshes built", "refit", "reused", "top levels built",
                   "culled instances / frame", "unused meshes / frame", "build ms"):
        table.add_column(column, justify="right")
    per_frame = max(len(reports), 1)
    table.add_row(
        str(sum(len(r.built) for r in reports)), str(sum(len(r.refit) for r in reports)),
        str(sum(len(r.reused) for r in reports)),
        str(sum(r.top_level == "built" for r in reports)),
        f"{sum(r.culled for r in reports) / per_frame:.1f}",
        f"{sum(len(r.skipped) for r in reports) / per_frame:.1f}",
        f"{sum(sum(r.timings_ms.values()) for r in reports):.1f}",
    )
    return table
