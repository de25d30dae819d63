"""`scenesort bake MESH`: ambient occlusion baked into a texture of a mesh with UVs,
without Blender, for asset pipelines.

    scenesort bake model.obj                                    # ao_bake.png, 1024^2, 64 spp
    scenesort bake model.glb --size 2048 --target-error 0.02 --out ao.npy --margin 16

Each texel centre that the mesh's texture coordinates cover (as Blender's bake: texel
centres, row 0 at v = 0) is a point of its triangle, shaded as `kernels.surface_ao` does
(the side the triangle's winding faces, the whole mesh occluding, `--smooth`: the file's
vertex normals as shading normals); a margin of `--margin` texels is grown around the
baked ones (Blender's Extend). `--out` takes .png (16-bit grey, AO 0..1 to 0..65535, no
gamma, the top row at v = 1 as image files store it), .exr (float32, needs the OpenEXR
package) or .npy (float32, row 0 at v = 0).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np
from scenesort.backend.commands import add_ao_option, ao_options, check_at_least

FORMATS = (".png", ".exr", ".npy")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("mesh", type=Path, help="a mesh file with texture coordinates "
                        "(.obj, .glb, .ply, ...)")  # fmt: skip
    parser.add_argument("--size", type=int, default=1024, help="texels per side (default 1024)")
    parser.add_argument("--margin", type=int, default=16,
                        help="texels grown around the baked ones (default 16)")
    parser.add_argument("--smooth", action="store_true",
                        help="shade with the file's vertex normals (default: flat)")
    mode = parser.add_mutually_exclusive_group()
    add_ao_option(mode, "spp")
    add_ao_option(mode, "target_error")
    for name in ("max_pixel_error", "max_spp", "distance", "seed", "sampler", "threads"):
        add_ao_option(parser, name)
    parser.add_argument("--out", type=Path, default=Path("ao_bake.png"),
                        help="the texture to write: .png, .exr or .npy (default ao_bake.png)")


def run(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.markup import escape

    console = Console()
    try:
        check_at_least(args, 1, "size")
        check_at_least(args, 0, "margin")
        if args.out.suffix.lower() not in FORMATS:
            raise ValueError(f"--out must end in one of {', '.join(FORMATS)}, got "
                             f"{str(args.out)!r}")  # fmt: skip
        return _bake(args, ao_options(args), console)
    except ValueError as exc:
        console.print(f"[red]error:[/red] {escape(str(exc))}")
        return 2


def load_uv_mesh(path: Path, smooth: bool) -> tuple[np.ndarray, ...]:
    """Vertices, triangles, their (M, 3, 2) texture coordinates and, with `smooth`, the
    (M, 3, 3) corner normals; ValueError naming what the file lacks."""
    import trimesh
    from scenesort.backend.render.scenes import load_mesh

    vertices, indices = load_mesh(path)
    mesh = trimesh.load(path, process=False, force="mesh")
    uv = getattr(getattr(mesh, "visual", None), "uv", None)
    if uv is None or len(uv) != len(vertices):
        raise ValueError(f"mesh {str(path)!r} has no texture coordinates: unwrap it (UVs) "
                         "and export them with the mesh")  # fmt: skip
    normals = None
    if smooth:
        normals = np.asarray(mesh.vertex_normals, np.float32)[indices]
    return vertices, indices, np.asarray(uv, np.float64)[indices], normals


def _bake(args: argparse.Namespace, options: Any, console: Any) -> int:
    from scenesort.backend.render import image
    from scenesort.backend.render.texels import extend_margin, rasterize

    from scenesort import kernels

    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    vertices, indices, uv, normals = load_uv_mesh(args.mesh, args.smooth)
    texels, triangles, u, v = rasterize(uv, args.size)
    if len(texels) == 0:
        raise ValueError(f"no texel centre of a {args.size}^2 image lies in a triangle of "
                         f"{str(args.mesh)!r}'s texture space: check its UVs (in 0..1) or "
                         "raise --size")  # fmt: skip
    timings["load and texels"] = (time.perf_counter() - t0) * 1e3
    bvh, timings["compile"], timings["build"] = image.build(vertices, indices)
    t0 = time.perf_counter()
    result = kernels.surface_ao(bvh, triangles, u, v, options, normals=normals)
    timings["ao"] = (time.perf_counter() - t0) * 1e3
    flat = np.zeros(args.size * args.size, np.float32)
    covered = np.zeros(args.size * args.size, bool)
    flat[texels], covered[texels] = result.ao, True
    t0 = time.perf_counter()
    texture = extend_margin(flat.reshape(args.size, args.size),
                            covered.reshape(args.size, args.size), args.margin)  # fmt: skip
    write(args.out, texture)
    timings["margin and write"] = (time.perf_counter() - t0) * 1e3
    stats = result.stats()
    rmse = "-" if stats.rmse_estimate is None else f"{stats.rmse_estimate:.4f}"
    console.print(f"{len(texels):,} texels of {len(indices):,} triangles | spp "
                  f"{stats.spp_mean:.1f} mean, {stats.spp_max} max | est. RMSE {rmse} | "
                  + " | ".join(f"{k} {v:.0f} ms" for k, v in timings.items()))  # fmt: skip
    console.print(f"wrote {args.out}")
    return 0


def write(path: Path, texture: np.ndarray) -> None:
    """`texture` ((size, size), row 0 at v = 0) as .npy, or as an image file (top row
    first): 16-bit grey PNG or float32 EXR."""
    path.parent.mkdir(parents=True, exist_ok=True)
    suffix = path.suffix.lower()
    if suffix == ".npy":
        np.save(path, texture.astype(np.float32))
        return
    top_first = np.ascontiguousarray(texture[::-1])
    if suffix == ".png":
        from PIL import Image

        grey = np.round(np.clip(top_first, 0.0, 1.0) * 65535.0).astype(np.uint16)
        Image.fromarray(grey).save(path, format="PNG")
        return
    try:
        import OpenEXR
    except ImportError:
        raise ValueError("--out .exr needs the OpenEXR package (pip install OpenEXR); or "
                         "write .png or .npy") from None  # fmt: skip
    channels = {"Y": top_first.astype(np.float32)}
    with OpenEXR.File({"type": OpenEXR.scanlineimage}, channels) as exr:
        exr.write(str(path))
