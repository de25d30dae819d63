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
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from scenesort.backend.commands import add_ao_option, ao_options, check_at_least


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
    # The AO settings, as AoOptions defines them (a mesh file has no smooth normals, so no
    # terminator offset); spp or an error target.
    mode = parser.add_mutually_exclusive_group()
    add_ao_option(mode, "spp")
    add_ao_option(mode, "target_error")
    for name in ("max_pixel_error", "max_spp", "distance", "seed", "sampler", "denoise",
                 "engine", "pixel_filter", "filter_width", "threads"):
        add_ao_option(parser, name)
    parser.add_argument("--out", type=Path, default=Path("ao.png"), help="8-bit PNG to write")
    parser.add_argument("--npy", type=Path, default=None, help="also write float32 AO (.npy)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def _check(args: argparse.Namespace) -> Any:
    """The render's AoOptions (checked there), after the image's own flags; ValueError
    naming the flag at fault."""
    check_at_least(args, 1, "width", "height")
    options = ao_options(args)
    from scenesort.backend.render import engine

    problem = engine.denoiser_problem() if options.denoise else None
    if problem is not None:
        raise ValueError(f"--denoise: {problem}")
    return options


def run(args: argparse.Namespace) -> int:
    from rich.console import Console

    console = Console()
    try:
        return _render(args, _check(args), console)
    except ValueError as exc:
        from rich.markup import escape

        console.print(f"[red]error:[/red] {escape(str(exc))}")  # "[denoise]" is no markup
        return 2


def _render(args: argparse.Namespace, options: Any, console: Any) -> int:
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
    shape = (camera.height, camera.width)
    if options.film_fallback is not None:
        console.print(f"[yellow]note:[/yellow] --filter-width: {options.film_fallback}")
    if options.filtered:
        t0 = time.perf_counter()
        film = _with_progress(lambda progress: image.render_film(bvh, camera, options,
                                                                 progress=progress),
                              console, not args.no_progress)
        timings["film"] = (time.perf_counter() - t0) * 1e3
        ao = film.ao
    else:
        result = _with_progress(lambda progress: image.render_ao(
            bvh, rays, options, image_shape=shape, progress=progress),
            console, not args.no_progress)
        ao = result.ao.reshape(camera.height, camera.width)

    t0 = time.perf_counter()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_bytes(encode_png(ao))  # the service's PNG: 8-bit grey, 0..1 -> 0..255
    if args.npy is not None:
        args.npy.parent.mkdir(parents=True, exist_ok=True)
        np.save(args.npy, ao.astype(np.float32))
    timings["write"] = (time.perf_counter() - t0) * 1e3

    table = (_film_table(scene, camera, film, options, timings) if options.filtered
             else _table(scene, camera, bvh, result, timings))
    console.print(table)
    written = f"{args.out}" + (f" and {args.npy}" if args.npy is not None else "")
    console.print(f"wrote {written}")
    return 0


def _with_progress(render: Callable[[Any], Any], console: Any, show: bool) -> Any:
    """`render(progress)` with a progress bar (progress None without one)."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    if not show:
        return render(None)
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

        return render(progress)


def _film_table(scene: Any, camera: Any, film: Any, options: Any,
                timings: dict[str, float]) -> Any:
    """The filtered render's timings: every sample's camera and occlusion rays are one
    phase ("film"), Warp's compile of the film kernel included on first use."""
    from rich.table import Table

    rmse = film.rmse_estimate
    title = (f"{scene.name}: {scene.triangles:,} triangles, {camera.width}x{camera.height}, "
             f"through {options.film}, spp mean {film.spp_mean:.1f} (max {film.spp_max}), "
             f"est. RMSE {'-' if rmse is None else f'{rmse:.4f}'} (AO units, covered pixels)")
    table = Table(title=title, min_width=len(title) + 4)
    for name, justify in (("phase", "left"), ("ms", "right"), ("rays", "right"),
                          ("MRays/s", "right")):
        table.add_column(name, justify=justify)
    total = sum(timings.values())
    for name, t in (*timings.items(), ("total", total)):
        n = film.rays if name in ("film", "total") else None
        rate = f"{n / t / 1e3:.2f}" if n and t > 0 else ""
        table.add_row(name, f"{t:.1f}", f"{n:,}" if n is not None else "", rate)
    return table


def _table(scene: Any, camera: Any, bvh: Any, result: Any, timings: dict[str, float]) -> Any:
    from rich.table import Table

    ms = result.timings_ms
    rays = result.rays
    stats = result.stats()
    rmse = stats.rmse_estimate
    title = (
        f"{scene.name}: {scene.triangles:,} triangles, {camera.width}x{camera.height}, "
        f"spp mean {stats.spp_mean:.1f} (max {stats.spp_max}), "
        f"est. RMSE {'-' if rmse is None else f'{rmse:.4f}'} (AO units, hit pixels"
        f"{', before denoising' if stats.denoised else ''})"
    )
    table = Table(title=title, min_width=len(title) + 4)
    table.add_column("phase")
    table.add_column("ms", justify="right")
    table.add_column("rays", justify="right")
    table.add_column("MRays/s", justify="right")

    def row(name: str, t: float, n: int | None = None) -> None:
        rate = f"{n / t / 1e3:.2f}" if n and t > 0 else ""
        table.add_row(name, f"{t:.1f}", f"{n:,}" if n is not None else "", rate)

    compile_ms = timings["compile"] + ms.compile  # the build's and the render's kernels
    row("load", timings["load"])
    row("compile", compile_ms)
    row("build", timings["build"])
    row("primary", ms.primary, rays.primary)
    row("occlusion", ms.occlusion, rays.occlusion)
    if ms.denoise is not None:
        row("denoise", ms.denoise)
    row("write", timings["write"])
    total = timings["load"] + compile_ms + timings["build"] + ms.total + timings["write"]
    row("total", total, rays.primary + rays.occlusion)
    return table
