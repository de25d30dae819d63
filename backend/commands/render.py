"""`scenesort render`: an ambient-occlusion render of a scene, with progress and timings.

    scenesort render                                   # the built-in default scene
    scenesort render --scene sponza --spp 64 --out sponza.png --npy sponza.npy
    scenesort render --scene mesh.ply --camera cam.json --target-error 0.02

`--scene` takes a mesh file or a shared scene's name; `--camera` a JSON file holding either
the wire form of `kernels.Camera` or a scenes.json look-at camera (position,
look_at, up, fov_y_deg). The PNG is 8-bit grey, AO scaled to 0..255 with no gamma (like
Cycles' AO pass); `--npy` also writes the float32 (height, width) image.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np
from scenesort.backend.commands import check_at_least

SAMPLERS = ("sobol", "random")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--scene",
        default=None,
        help="a mesh file (.ply, .obj, ...) or a shared scene name (default: the built-in scene)",
    )
    parser.add_argument(
        "--camera",
        type=Path,
        default=None,
        help="camera JSON: Camera wire form or {position, look_at, up, "
        "fov_y_deg} (default: the scene's camera, or one framing the mesh)",
    )
    parser.add_argument("--width", type=int, default=None, help="pixels across (default 640)")
    parser.add_argument("--height", type=int, default=None, help="pixels down (default 480)")
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--spp", type=int, default=16, help="samples per pixel (default 16)")
    mode.add_argument(
        "--target-error",
        type=float,
        default=None,
        help="adaptive: stop once the image's estimated RMSE over hit pixels (AO in [0, 1]) is "
        "below; the achieved RMSE is within [0.7, 1.0]x of it in >= 95%% of renders",
    )
    parser.add_argument(
        "--max-pixel-error",
        type=float,
        default=None,
        help="adaptive: stop each pixel once its 95%% interval half-width is below",
    )
    parser.add_argument(
        "--max-spp", type=int, default=1024, help="adaptive: most samples per pixel (default 1024)"
    )
    parser.add_argument(
        "--distance",
        type=float,
        default=None,
        help="occlusion distance (default: 0.1 of the scene box diagonal)",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--sampler", choices=SAMPLERS, default="sobol")
    parser.add_argument(
        "--denoise",
        action="store_true",
        help='denoise with Intel OIDN (pip install "scenesort[denoise]"); the estimated '
        "RMSE stays the raw render's",
    )
    parser.add_argument("--engine", choices=("bvh", "dacrt"), default="bvh",
                        help="trace through the BVH, or with the task-pool DACRT (no BVH)")
    parser.add_argument("--threads", type=int, default=None, help="host threads (default: all)")
    parser.add_argument("--out", type=Path, default=Path("ao.png"), help="8-bit PNG to write")
    parser.add_argument("--npy", type=Path, default=None, help="also write float32 AO (.npy)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def _check(args: argparse.Namespace) -> None:
    check_at_least(args, 1, "width", "height", "spp")
    if args.distance is not None and not args.distance > 0:
        raise ValueError(f"--distance must be > 0, got {args.distance}")
    for name in ("target_error", "max_pixel_error"):
        value = getattr(args, name)
        if value is not None and not 0 < value < 1:
            raise ValueError(f"--{name.replace('_', '-')} must be in (0, 1), got {value}")
    from scenesort.backend.render import engine

    problem = engine.denoiser_problem() if args.denoise else None
    if problem is not None:
        raise ValueError(f"--denoise: {problem}")


def run(args: argparse.Namespace) -> int:
    from rich.console import Console

    console = Console()
    try:
        _check(args)
        return _render(args, console)
    except ValueError as exc:
        from rich.markup import escape

        console.print(f"[red]error:[/red] {escape(str(exc))}")  # "[denoise]" is no markup
        return 2


def _render(args: argparse.Namespace, console: Any) -> int:
    # The engine is imported here, not with the module: `scenesort render --help` stays quick.
    from scenesort.backend.render import image
    from scenesort.backend.render.scenes import load_camera, load_scene
    from scenesort.backend.wire.binary import encode_png

    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    scene = load_scene(args.scene, args.width, args.height)
    camera = scene.camera
    if args.camera is not None:
        camera = load_camera(args.camera, camera.width, camera.height)
    rays = camera.rays()
    timings["load"] = (time.perf_counter() - t0) * 1e3

    bvh, timings["compile"], timings["build"] = image.build(scene.vertices, scene.indices)
    settings = dict(
        spp=args.spp,
        distance=args.distance,
        seed=args.seed,
        target_error=args.target_error,
        max_pixel_error=args.max_pixel_error,
        engine=args.engine,
        threads=args.threads,
        max_spp=args.max_spp,
        sampler=args.sampler,
        denoise=args.denoise,
        image_shape=(camera.height, camera.width),
    )
    result = _with_progress(bvh, rays, settings, console, not args.no_progress)
    ao = result.ao.reshape(camera.height, camera.width)

    t0 = time.perf_counter()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_bytes(encode_png(ao))  # the service's PNG: 8-bit grey, 0..1 -> 0..255
    if args.npy is not None:
        args.npy.parent.mkdir(parents=True, exist_ok=True)
        np.save(args.npy, ao.astype(np.float32))
    timings["write"] = (time.perf_counter() - t0) * 1e3

    console.print(_table(scene, camera, bvh, result, timings))
    written = f"{args.out}" + (f" and {args.npy}" if args.npy is not None else "")
    console.print(f"wrote {written}")
    return 0


def _with_progress(bvh: Any, rays: tuple, settings: dict, console: Any, show: bool) -> Any:
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
    from scenesort.backend.render import image

    if not show:
        return image.render_ao(bvh, rays, **settings)
    columns = (
        TextColumn("{task.description:<10}"),
        BarColumn(),
        TextColumn("{task.percentage:>5.1f}%"),
        TimeElapsedColumn(),
    )
    with Progress(*columns, console=console, transient=True) as bar:
        task = bar.add_task("primary", total=1.0)

        def progress(fraction: float, phase: str) -> None:
            bar.update(task, completed=fraction, description=phase)

        return image.render_ao(bvh, rays, progress=progress, **settings)


def _table(scene: Any, camera: Any, bvh: Any, result: Any, timings: dict[str, float]) -> Any:
    from rich.table import Table

    ms = result.timings_ms
    rays = result.rays
    stats = result.stats()
    rmse = stats["rmse_estimate"]
    title = (
        f"{scene.name}: {scene.triangles:,} triangles, {camera.width}x{camera.height}, "
        f"spp mean {stats['spp_mean']:.1f} (max {stats['spp_max']}), "
        f"est. RMSE {'-' if rmse is None else f'{rmse:.4f}'} (AO units, hit pixels"
        f"{', before denoising' if stats['denoised'] else ''})"
    )
    table = Table(title=title, min_width=len(title) + 4)
    table.add_column("phase")
    table.add_column("ms", justify="right")
    table.add_column("rays", justify="right")
    table.add_column("MRays/s", justify="right")

    def row(name: str, t: float, n: int | None = None) -> None:
        rate = f"{n / t / 1e3:.2f}" if n and t > 0 else ""
        table.add_row(name, f"{t:.1f}", f"{n:,}" if n is not None else "", rate)

    compile_ms = timings["compile"] + ms.get("compile", 0.0)  # build's and render's kernels
    row("load", timings["load"])
    row("compile", compile_ms)
    row("build", timings["build"])
    row("primary", ms["primary"], rays["primary"])
    row("occlusion", ms["occlusion"], rays["occlusion"])
    if "denoise" in ms:
        row("denoise", ms["denoise"])
    row("write", timings["write"])
    total = timings["load"] + compile_ms + timings["build"] + ms["total"] + timings["write"]
    row("total", total, rays["primary"] + rays["occlusion"])
    return table
