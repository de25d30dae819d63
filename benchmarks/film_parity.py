"""The engine's filtered render (`kernels.render.filtered.render_film`) against Cycles' AO
pass at Cycles' default pixel filter (Blackman-Harris 1.5 px), edges and alpha included.

    .venv/bin/python benchmarks/film_parity.py             # 64x48, N = 64
    .venv/bin/python benchmarks/film_parity.py --size 96 72 --n 64 256

The scene is benchmarks/cycles.py's parity scene (flat and smooth objects, silhouettes
against the transparent background). Triangles, normals and terminator offsets come from
the add-on's export and the camera from its camera_dict, so both renderers see the same
scene; render_film is called directly (F12 sends the same filter through the service:
tests/addon/test_film.py).

For each N: a Cycles reference at 16N spp (seed 0), Cycles at N (seed 1) and render_film at
N (seed 2). Cycles' AO pass is accumulated by the samples that hit a surface only, so it
is premultiplied by coverage: scenesort's comparable value is ao - (1 - alpha) (its misses
count 1.0). RMSE against the reference over covered pixels (reference alpha > 0), over
edge pixels (reference alpha strictly in (0, 1)), and of alpha over the whole image.
Floor (issue 32): scenesort's RMSE at most 1.25x Cycles' at the same N.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
# As in benchmarks/cycles.py: that file must not stand in for Blender's `cycles` add-on.
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != HERE]
sys.path[:0] = [str(HERE.parent), str(HERE.parent / "tests" / "addon")]

import bpy  # noqa: E402
import numpy as np  # noqa: E402
from cycles_reference import render_cycles_ao  # noqa: E402
from scenesort.kernels.render.filtered import render_film  # noqa: E402

import addon  # noqa: E402
from addon import camera, export  # noqa: E402
from benchmarks.cycles import PARITY_RATIO, new_scene, parity_scene  # noqa: E402
from scenesort import kernels  # noqa: E402

FILM = ("BLACKMAN_HARRIS", 1.5)


def rmse(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    return float(np.sqrt(np.mean((a - b)[mask] ** 2)))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", type=int, nargs=2, default=(64, 48))
    parser.add_argument("--n", type=int, nargs="+", default=[64])
    args = parser.parse_args(argv)
    ok = True
    with tempfile.TemporaryDirectory(prefix="scenesort-film-") as tmp:
        scene = new_scene()
        try:
            parity_scene(scene, *args.size)
            depsgraph = bpy.context.evaluated_depsgraph_get()
            mesh = export.export_scene(depsgraph)
            cam = kernels.Camera.from_dict(camera.camera_dict(scene, depsgraph))
            bvh = kernels.build_bvh(mesh.vertices, mesh.indices)
            offsets = mesh.terminator_offsets
            distance = scene.world.light_settings.distance
            print("| N | pixels: covered / edge | AO RMSE covered: scenesort / Cycles / ratio "
                  "| AO RMSE edge: scenesort / Cycles / ratio | alpha RMSE: scenesort / "
                  "Cycles / ratio | floor |")
            for n in args.n:
                ref, ref_a, _ = render_cycles_ao(scene, Path(tmp) / f"ref{n}", 16 * n, 0, FILM)
                cyc, cyc_a, _ = render_cycles_ao(scene, Path(tmp) / f"cyc{n}", n, 1, FILM)
                ours = render_film(bvh, cam, spp=n, seed=2, distance=distance,
                                   normals=mesh.normals,
                                   terminator_offset=0.1 if offsets is None else offsets,
                                   pixel_filter=FILM[0], filter_width=FILM[1])
                ours_pass = ours.ao - (1.0 - ours.alpha)
                covered, edge = ref_a > 0, (ref_a > 0) & (ref_a < 1)
                everywhere = np.ones_like(covered)
                cells, met = [], True
                for mine_img, theirs_img, truth, mask in (
                        (ours_pass, cyc, ref, covered), (ours_pass, cyc, ref, edge),
                        (ours.alpha, cyc_a, ref_a, everywhere)):
                    mine, theirs = rmse(mine_img, truth, mask), rmse(theirs_img, truth, mask)
                    met &= mine <= PARITY_RATIO * theirs
                    cells.append(f"{mine:.4f} / {theirs:.4f} / {mine / theirs:.2f}")
                ok &= met
                print(f"| {n} | {int(covered.sum())} / {int(edge.sum())} | "
                      + " | ".join(cells) + f" | {'met' if met else 'NOT met'} |", flush=True)
                bias = float((ours_pass - ref)[edge].mean())
                print(f"  edge bias (scenesort - reference): {bias:+.4f}")
        finally:
            addon.unregister()
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
