"""scenesort's F12 against Cycles' own AO pass, in one headless Blender (bpy) session:
parity of the images and the time of F12.

    .venv/bin/python benchmarks/cycles.py              # N = 64 and 256; dragon at 320x240
    .venv/bin/python benchmarks/cycles.py --quick      # N = 64 only, smaller images, 1 round
    .venv/bin/python benchmarks/cycles.py --rounds 5   # more interleaved speed rounds
    .venv/bin/python benchmarks/cycles.py --no-docs    # print only

Parity: a floor and a cube (flat-shaded), a low-poly UV sphere and a
subdivided cube (smooth-shaded), World AO distance 1.5, default terminator offset 0.1.
On clean hit pixels (the pixel and its 8 neighbours hit the same kind of object in both
renderers), the RMSE of scenesort at N spp against a Cycles reference at 16N spp must be at
most 1.25x the RMSE of Cycles at N spp (another seed) against the same reference, for flat
and smooth objects separately; background alpha must be exactly 0 in both (on pixels with
no object in or next to them: Cycles' 0.01-pixel filter still lets a silhouette crossing
near a pixel's centre cover 1/N of it).

Speed: the shared Stanford dragon (100,000 triangles, smooth-shaded) on a floor,
its scenes.json camera, World AO distance 2, 64 spp. The service is already running (a
tiny warm-up render started it and loaded its kernels); the first F12 includes export,
upload and BVH build; the second F12 of the unchanged scene reuses both. Floors: first F12
at most 0.5x Cycles' F12 on the CPU with the same samples, later F12 at most 0.2x Cycles'.
Cycles' settings are printed with the table (`cycles_reference.SETTINGS`) with Blender's
default light paths (max bounces 12); a third column is Cycles with max bounces 0 (no path
tracing beyond the AO pass, its fastest F12 of this pass). The parity renders use max
bounces 0: the AO pass does not depend on them.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
# This file must not stand in for Blender's own `cycles` add-on: its folder is not searched.
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != HERE]

import bpy  # noqa: E402  (before bmesh, which only bpy makes importable)
import numpy as np  # noqa: E402

REPO = HERE.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests" / "addon"))  # the Cycles judge and helpers of the tests

import bmesh  # noqa: E402
from cycles_reference import (  # noqa: E402
    SETTINGS,
    channel,
    clean_pixels,
    exr_channels,
    render_cycles_ao,
)
from scenesort.backend.render.scenes import shared_scenes_dir  # noqa: E402

import addon  # noqa: E402
from addon import export, prefs, service  # noqa: E402
from benchmarks.docs_section import write_section  # noqa: E402

PARITY_RATIO = 1.25
FIRST_RATIO, LATER_RATIO = 0.5, 0.2
PARITY_DISTANCE, SPEED_DISTANCE = 1.5, 2.0


# --- scenes ---------------------------------------------------------------------------


def _mesh(name: str, build, smooth: bool) -> bpy.types.Mesh:
    mesh = bpy.data.meshes.new(name)
    bm = bmesh.new()
    build(bm)
    for face in bm.faces:
        face.smooth = smooth
    bm.to_mesh(mesh)
    bm.free()
    return mesh


def _add(scene, name: str, mesh, location) -> bpy.types.Object:
    obj = bpy.data.objects.new(name, mesh)
    obj.location = location
    scene.collection.objects.link(obj)
    return obj


def _camera(scene, position, look_at, up, fov_y_deg: float, width: int, height: int) -> None:
    """A pinhole camera at `position` looking at `look_at` (vertical field of view)."""
    forward = np.subtract(look_at, position, dtype=np.float64)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    cam = bpy.data.cameras.new("Camera")
    cam.sensor_fit = "VERTICAL"
    cam.angle_y = math.radians(fov_y_deg)
    obj = bpy.data.objects.new("Camera", cam)
    matrix = np.eye(4)
    matrix[:3, 0], matrix[:3, 1], matrix[:3, 2], matrix[:3, 3] = right, true_up, -forward, position
    obj.matrix_world = matrix.T.tolist()  # bpy reads a nested list column by column
    scene.collection.objects.link(obj)
    scene.camera = obj
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100


def new_scene() -> bpy.types.Scene:
    """An empty scene with the add-on registered (F12 starts the service), a World, EXR
    output and Film Transparent."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon.register()
    scene = bpy.context.scene
    scene.world = bpy.data.worlds.new("World")
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    scene.render.film_transparent = True
    prefs.preferences(bpy.context).start_on_render = True
    return scene


def clear(scene: bpy.types.Scene) -> None:
    """Remove every object (the service keeps running)."""
    for obj in list(scene.objects):
        bpy.data.objects.remove(obj)


def parity_scene(scene, width: int, height: int) -> None:
    clear(scene)
    scene.world.light_settings.distance = PARITY_DISTANCE
    # F12 renders through the scene's pixel filter: the pixel-centre one Cycles gets here
    scene.cycles.pixel_filter_type, scene.cycles.filter_width = "GAUSSIAN", 0.01
    _add(scene, "Floor", _mesh("Floor", lambda bm: bmesh.ops.create_grid(
        bm, x_segments=6, y_segments=6, size=4.0), smooth=False), (0, 0, 0))
    _add(scene, "Cube", _mesh("Cube", lambda bm: bmesh.ops.create_cube(bm, size=1.0),
                              smooth=False), (1.6, 0.8, 0.5))
    _add(scene, "Sphere", _mesh("Sphere", lambda bm: bmesh.ops.create_uvsphere(
        bm, u_segments=12, v_segments=6, radius=1.0), smooth=True), (-1.3, 0.0, 1.0))
    subd = _add(scene, "Subd", _mesh("Subd", lambda bm: bmesh.ops.create_cube(bm, size=1.0),
                                     smooth=True), (0.3, -1.2, 0.5))
    mod = subd.modifiers.new("Subdivision", "SUBSURF")
    mod.levels = mod.render_levels = 2  # the same mesh in the viewport export (classes)
    _camera(scene, (0.0, -6.0, 3.6), (0.0, 0.0, 0.6), (0, 0, 1), 45.0, width, height)


def dragon_scene(scene, width: int, height: int) -> int:
    """The dragon on a floor; its triangle count."""
    folder = shared_scenes_dir()
    if folder is None:
        raise SystemExit("no shared scenes folder: set $SCENESORT_SCENES")
    clear(scene)
    scene.world.light_settings.distance = SPEED_DISTANCE
    before = set(bpy.data.objects)
    bpy.ops.wm.ply_import(filepath=str(folder / "dragon.ply"), forward_axis="NEGATIVE_Z",
                          up_axis="Y")  # keep the file's coordinates (+Y up)
    (dragon,) = set(bpy.data.objects) - before
    dragon.data.shade_smooth()
    s = 20.0
    floor = _mesh("Floor", lambda bm: None, smooth=False)
    floor.from_pydata([(-s, 0, -s), (s, 0, -s), (s, 0, s), (-s, 0, s)], [], [(0, 3, 2, 1)])
    _add(scene, "Floor", floor, (0, 0, 0))
    _camera(scene, (9.28, 14.24, 30.92), (0.0, 4.97, 0.0), (0, 1, 0), 35.0, width, height)
    return len(dragon.data.polygons) + 2


# --- renders ----------------------------------------------------------------------------


def scenesort_f12(scene, path: Path, spp: int, seed: int) -> tuple[np.ndarray, np.ndarray, float]:
    """F12 with the scenesort AO engine: (AO, alpha, seconds), row 0 at the top."""
    scene.render.engine = "SCENESORT"
    scene.scenesort.spp, scene.scenesort.seed = spp, seed
    scene.render.filepath = str(path)
    start = time.perf_counter()
    assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
    seconds = time.perf_counter() - start
    channels = exr_channels(path.with_suffix(".exr"))
    return channel(channels, "R"), channel(channels, "A"), seconds


def f12_seconds(scene, engine: str) -> float:
    """The wall time of one F12 (no file written)."""
    scene.render.engine = engine
    start = time.perf_counter()
    assert bpy.ops.render.render() == {"FINISHED"}
    return time.perf_counter() - start


def pixel_classes(scene) -> np.ndarray:
    """Per pixel (row 0 at the top): -1 background, 0 flat, 1 smooth, from the exported
    triangles the camera rays hit first (the engine's own camera model)."""
    from addon import camera
    from scenesort import kernels

    depsgraph = bpy.context.evaluated_depsgraph_get()
    mesh = export.export_scene(depsgraph)
    o, d, tmin, tmax = kernels.Camera.from_dict(camera.camera_dict(scene, depsgraph)).rays()
    hits = kernels.trace(kernels.build_bvh(mesh.vertices, mesh.indices), o, d, tmin, tmax)
    smooth = np.zeros(mesh.triangles, bool) if mesh.normals is None else (
        np.abs(mesh.normals).reshape(mesh.triangles, -1).max(axis=1) > 0)
    out = np.where(hits.hit, smooth[np.maximum(hits.triangle, 0)].astype(int), -1)
    return out.reshape(scene.render.resolution_y, scene.render.resolution_x)


def clean(classes: np.ndarray, kind: int, alphas: list[np.ndarray]) -> np.ndarray:
    """Pixels of `kind` whose 8 neighbours are that kind too, covered in every render."""
    same = classes == kind
    for a in alphas:
        same &= a == 1.0
    return clean_pixels(same)


def rmse(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    return float(np.sqrt(np.mean((a - b)[mask] ** 2)))


# --- the two measurements ---------------------------------------------------------------


def parity(scene, work: Path, ns: list[int], width: int,
           height: int) -> tuple[list[str], bool]:
    parity_scene(scene, width, height)
    classes = pixel_classes(scene)
    rows, ok = [], True
    for n in ns:
        ref, ref_alpha, ref_s = render_cycles_ao(scene, work / f"ref{n}", 16 * n, seed=0)
        cyc, cyc_alpha, _ = render_cycles_ao(scene, work / f"cycles{n}", n, seed=1)
        ours, our_alpha, _ = scenesort_f12(scene, work / f"ours{n}", n, seed=2)
        background = clean_pixels(classes < 0)  # a silhouette near a pixel may cover 1/N
        alpha_zero = bool(np.all(our_alpha[background] == 0.0) and
                          np.all(cyc_alpha[background] == 0.0))
        ok &= alpha_zero
        for kind, name in ((0, "flat"), (1, "smooth")):
            mask = clean(classes, kind, [ref_alpha, cyc_alpha, our_alpha])
            ours_rmse, cycles_rmse = rmse(ours, ref, mask), rmse(cyc, ref, mask)
            ratio = ours_rmse / cycles_rmse
            met = ratio <= PARITY_RATIO and alpha_zero
            ok &= met
            bias = float((ours - ref)[mask].mean())
            rows.append(f"| {n} | {16 * n} | {name} | {int(mask.sum())} | {ours_rmse:.4f} | "
                        f"{cycles_rmse:.4f} | {ratio:.2f} | {bias:+.4f} | "
                        f"{'yes' if alpha_zero else 'NO'} | {'met' if met else 'NOT met'} |")
        print(rows[-2], rows[-1], f"(reference {ref_s:.1f} s)", sep="\n", flush=True)
    return rows, ok


def speed(scene, width: int, height: int, spp: int,
          rounds: int) -> tuple[list[str], bool, int, list[str]]:
    """Interleaved rounds (the machine is shared: medians of rounds taken side by side):
    each round moves the dragon by 1 mm, so the scene is new to the service (its first F12
    uploads and builds), then F12s it again unchanged, then times Cycles' F12 at Blender's
    default light paths and at max bounces 0. Run after `parity`, whose F12s started the
    service and loaded its kernels."""
    assert service.running()
    triangles = dragon_scene(scene, width, height)
    dragon = next(o for o in scene.objects if o.type == "MESH" and o.name != "Floor")
    scene.scenesort.spp = scene.cycles.samples = spp
    cycles = scene.cycles
    cycles.device, cycles.use_adaptive_sampling, cycles.use_denoising = "CPU", False, False
    cycles.pixel_filter_type, cycles.filter_width = "GAUSSIAN", 0.01
    scene.view_layers[0].use_pass_ambient_occlusion = True
    default_bounces = cycles.max_bounces
    times: dict[str, list[float]] = {"first": [], "later": [], "cycles": [], "lean": []}
    log = []
    for r in range(rounds):
        dragon.location.x = 1e-3 * (r + 1)  # another scene: uploaded and built again
        times["first"].append(f12_seconds(scene, "SCENESORT"))
        times["later"].append(f12_seconds(scene, "SCENESORT"))
        cycles.max_bounces = default_bounces
        times["cycles"].append(f12_seconds(scene, "CYCLES"))
        cycles.max_bounces = 0  # only the AO pass's work: Cycles' fastest F12 of this pass
        times["lean"].append(f12_seconds(scene, "CYCLES"))
        log.append(f"round {r}: " + ", ".join(f"{k} {v[-1]:.2f} s" for k, v in times.items())
                   + f" (load {os.getloadavg()[0]:.2f})")
        print(log[-1], flush=True)
    cycles.max_bounces = default_bounces
    med = {k: statistics.median(v) for k, v in times.items()}
    rows, met = [], []
    for key, label, floor in (("first", "first F12 (upload and build included)", FIRST_RATIO),
                              ("later", "later F12 (unchanged scene)", LATER_RATIO)):
        ratio = med[key] / med["cycles"]
        met.append(ratio <= floor)
        rows.append(f"| {label} | {med[key]:.2f} | {med['cycles']:.2f} | {ratio:.3f} | "
                    f"{floor} | {'met' if met[-1] else 'NOT met'} | {med['lean']:.2f} | "
                    f"{med[key] / med['lean']:.3f} |")
    print(*rows, sep="\n", flush=True)
    return rows, all(met), triangles, log


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true",
                        help="N = 64 only, parity 48x36, speed at 160x120")
    parser.add_argument("--rounds", type=int, default=None,
                        help="interleaved speed rounds, medians reported (default 3; quick: 1)")
    parser.add_argument("--no-docs", action="store_true", help="print only")
    args = parser.parse_args(argv)
    rounds = args.rounds or (1 if args.quick else 3)
    command = " ".join(["benchmarks/cycles.py", *(argv if argv is not None else sys.argv[1:])])
    ns = [64] if args.quick else [64, 256]
    size = (48, 36) if args.quick else (64, 48)
    shot = (160, 120) if args.quick else (320, 240)
    with tempfile.TemporaryDirectory(prefix="scenesort-cycles-") as tmp:
        scene = new_scene()
        try:
            parity_rows, parity_ok = parity(scene, Path(tmp), ns, *size)
            speed_rows, speed_ok, triangles, rounds_log = speed(scene, *shot, 64, rounds)
        finally:
            addon.unregister()
    load = os.getloadavg()
    cores = os.cpu_count()
    body = "\n\n".join([
        "## scenesort's F12 against Cycles' AO pass",
        "Produced by `benchmarks/cycles.py` (scenes and rules in its docstring). scenesort "
        "shades with Blender's corner normals and Cycles' shadow-terminator offset, so "
        "smooth-shaded objects are compared as well as flat ones. Cycles' settings: "
        f"{SETTINGS}; max bounces 0 for the parity renders (the AO pass does not depend on "
        "them), Blender's default 12 in the speed table unless its column says 0.",
        f"Command: `.venv/bin/python {command}`; {cores} cores, load average "
        f"{load[0]:.2f} / {load[1]:.2f} / {load[2]:.2f} (1, 5, 15 min) at the end of the run.",
        f"### Parity: RMSE against a 16N-spp Cycles reference, {size[0]}x{size[1]}, clean hit "
        "pixels",
        "| N spp | reference spp | objects | pixels | scenesort RMSE | Cycles RMSE | ratio | "
        "scenesort mean bias | background alpha 0 | floor (ratio <= 1.25) |\n"
        "|---:|---:|---|---:|---:|---:|---:|---:|---|---|\n" + "\n".join(parity_rows),
        f"### Speed: the dragon ({triangles:,} triangles, smooth) at {shot[0]}x{shot[1]}, "
        f"64 spp, service running; medians of {rounds} interleaved rounds (seconds)",
        "| F12 | scenesort s | Cycles s | ratio | floor | | Cycles s, max bounces 0 | "
        "ratio to it |\n"
        "|---|---:|---:|---:|---:|---|---:|---:|\n" + "\n".join(speed_rows),
        "```\n" + "\n".join(rounds_log) + "\n```",
    ])
    print(body)
    if not args.no_docs:
        write_section("cycles", body)
    return 0 if parity_ok and speed_ok else 1


if __name__ == "__main__":
    sys.exit(main())
