"""`scenesort render-frames`: render a frame bundle (File > Export > scenesort animation).

    scenesort render-frames BUNDLE --out DIR [--frames 1-40,50] [--resume] [--threads N]

Writes `DIR/<frame>.png` (8-bit AO, the service's PNG) and `DIR/<frame>.npy` (float32 AO,
row 0 at the top) per frame with a progress bar, then a table of what the frames built:
meshes built, refit or reused, and top levels built (backend/frames.py's skip rules).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bundle", type=Path, help="the bundle's folder (holds manifest.json)")
    parser.add_argument("--out", type=Path, required=True, help="folder for the frames")
    parser.add_argument("--frames", default=None,
                        help="which frames, e.g. 1-40,50 (default: all in the bundle)")
    parser.add_argument("--resume", action="store_true",
                        help="skip frames whose files are already in --out")
    parser.add_argument("--threads", type=int, default=None, help="host threads (default: all)")
    parser.add_argument("--device", default="cpu", help="Warp device (default cpu)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")


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

    from backend.frames import render_frames

    console = Console()
    try:
        if args.threads is not None and args.threads < 1:
            raise ValueError(f"--threads must be >= 1, got {args.threads}")
        frames = None if args.frames is None else parse_frames(args.frames)
        start = time.perf_counter()
        done = render_frames(args.bundle, args.out, frames=frames, resume=args.resume,
                             threads=args.threads, progress=not args.no_progress,
                             device=args.device)
    except ValueError as exc:  # BundleError included: it names the file and the field
        console.print(f"[red]error:[/red] {exc}")
        return 2
    console.print(_table(done, time.perf_counter() - start))
    console.print(f"wrote {len(done)} frames to {args.out}")
    return 0


def _table(done: list[tuple[int, Any]], seconds: float) -> Any:
    from rich.table import Table

    reports = [r for _, r in done if r is not None]
    table = Table(title=f"{len(reports)} frames rendered ({len(done) - len(reports)} "
                  f"skipped) in {seconds:.1f} s")
    for column in ("meshes built", "refit", "reused", "top levels built", "build ms"):
        table.add_column(column, justify="right")
    table.add_row(
        str(sum(len(r.built) for r in reports)), str(sum(len(r.refit) for r in reports)),
        str(sum(len(r.reused) for r in reports)),
        str(sum(r.top_level == "built" for r in reports)),
        f"{sum(sum(r.timings_ms.values()) for r in reports):.1f}",
    )
    return table
