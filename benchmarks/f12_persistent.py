"""A later F12 of an unchanged scene of subdivided, smooth objects, with and without
Persistent Data, against Cycles' F12 with and without it, in one headless Blender (bpy)
session with a real service.

    .venv/bin/python benchmarks/f12_persistent.py [--level 4] [--rounds 5] [--quick]
        [--no-docs]

The scene: six Suzannes, smooth-shaded, each under a Subdivision modifier at render level
`--level` (4: 1.49 M triangles), on a ground plane; 320x240, 64 spp, the Film's default
Blackman-Harris 1.5 px filter in both renderers, World AO distance 1. Cycles on the CPU,
its AO pass on, no adaptive sampling, no denoising, Blender's default light paths.

Changing a scene's engine or turning its Persistent Data off frees what Blender keeps, and
so does an F12 of another scene (measured: the next F12 gets a new depsgraph), so the four
cases are four scenes sharing the same objects (linked copies): scenesort and Cycles, each
with Persistent Data off and on, and each round F12s each scene twice in a row and times
the second F12 (the first refills what the other scenes' F12s freed). After a warm-up
round (the service started, the scene uploaded and built); medians of the rounds. For
scenesort's F12s, the split of the time: export (Blender's process), the service's job
(trace), and the rest (Blender's depsgraph, the Render Result).

Floor (issue 33): a later F12 of the unchanged scene at most 0.15x Cycles' F12 (Persistent
Data off, as Blender starts) with the same samples.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != HERE]

import bpy  # noqa: E402

REPO = HERE.parent
sys.path.insert(0, str(REPO))

import addon  # noqa: E402
from addon import persistent, pipeline, prefs  # noqa: E402
from benchmarks.docs_section import write_section  # noqa: E402

FLOOR_RATIO = 0.15
WIDTH, HEIGHT, SPP = 320, 240, 64
CASES = ("scenesort", "scenesort kept", "Cycles", "Cycles persistent")


def build_scene(level: int) -> int:
    """The scene (see the docstring) as four linked scenes named after CASES; its
    triangles at render level."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon.register()
    scene = bpy.context.scene
    scene.name = CASES[0]
    scene.world = bpy.data.worlds.new("World")
    scene.world.light_settings.distance = 1.0
    for k in range(6):
        bpy.ops.mesh.primitive_monkey_add(location=((k % 3) * 2.5 - 2.5, (k // 3) * 2.5, 1.0))
        obj = bpy.context.active_object
        mod = obj.modifiers.new("Subdivision", "SUBSURF")
        mod.levels, mod.render_levels = 1, level
        obj.data.shade_smooth()
    bpy.ops.mesh.primitive_plane_add(size=20)
    cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    cam.location, cam.rotation_euler = (0.0, -9.0, 6.0), (math.radians(60), 0.0, 0.0)
    scene.collection.objects.link(cam)
    scene.camera = cam
    render = scene.render
    render.resolution_x, render.resolution_y, render.resolution_percentage = WIDTH, HEIGHT, 100
    scene.scenesort.spp = scene.cycles.samples = SPP
    cycles = scene.cycles
    cycles.device, cycles.use_adaptive_sampling, cycles.use_denoising = "CPU", False, False
    scene.view_layers[0].use_pass_ambient_occlusion = True
    prefs.preferences(bpy.context).start_on_render = True
    for name in CASES[1:]:
        scene.copy().name = name  # the same objects and collections (a linked copy)
    for name in CASES:
        s = bpy.data.scenes[name]
        s.render.engine = "CYCLES" if name.startswith("Cycles") else "SCENESORT"
        s.render.use_persistent_data = name in ("scenesort kept", "Cycles persistent")
    return 6 * 968 * 4**level + 2


class Split:
    """Where a scenesort F12's time went: the export and the service's job."""

    def __init__(self) -> None:
        self.export_s = self.job_s = 0.0
        for name in ("export_scene", "export_instances"):
            setattr(persistent, name, self._timed(getattr(persistent, name), "export_s"))
        pipeline.render_job = self._timed(pipeline.render_job, "job_s")

    def _timed(self, real, field: str):  # noqa: ANN001, ANN202
        def timed(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
            start = time.perf_counter()
            try:
                return real(*args, **kwargs)
            finally:
                setattr(self, field, time.perf_counter() - start)
        return timed


def f12(name: str, split: Split) -> dict:
    split.export_s = split.job_s = 0.0
    start = time.perf_counter()
    assert bpy.ops.render.render(scene=name) == {"FINISHED"}
    seconds = time.perf_counter() - start
    return {"s": seconds, "export": split.export_s, "job": split.job_s}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--level", type=int, default=4, help="subdivision render level")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--quick", action="store_true", help="level 2, 1 round, no docs")
    parser.add_argument("--no-docs", action="store_true", help="print only")
    args = parser.parse_args(argv)
    level, rounds = (2, 1) if args.quick else (args.level, args.rounds)
    command = " ".join(["benchmarks/f12_persistent.py",
                        *(argv if argv is not None else sys.argv[1:])])
    triangles = build_scene(level)
    split = Split()
    runs: dict[str, list[dict]] = {name: [] for name in CASES}
    log = []
    try:
        for name in CASES:  # warm-up: service, upload, build, Cycles' kernels
            f12(name, split)
        for r in range(rounds):
            for name in CASES:
                f12(name, split)  # what this scene keeps, made again
                runs[name].append(f12(name, split))
            log.append(f"round {r}: " + ", ".join(f"{k} {v[-1]['s']:.2f} s"
                                                  for k, v in runs.items())
                       + f" (load {os.getloadavg()[0]:.2f})")
            print(log[-1], flush=True)
    finally:
        addon.unregister()
    med = {name: {k: statistics.median(x[k] for x in got) for k in got[0]}
           for name, got in runs.items()}
    cycles, cycles_kept = med["Cycles"]["s"], med["Cycles persistent"]["s"]
    rows, met = [], True
    for name in CASES:
        m = med[name]
        ours = not name.startswith("Cycles")
        ratio = m["s"] / cycles
        ok = ratio <= FLOOR_RATIO
        if name == "scenesort kept":
            met = ok
        split_cols = (f"{m['export']:.2f} | {m['job']:.2f} | "
                      f"{m['s'] - m['export'] - m['job']:.2f}") if ours else "- | - | -"
        verdict = ("met" if ok else "NOT met") if name == "scenesort kept" else ""
        rows.append(f"| {name} | {'on' if 'kept' in name or 'persistent' in name else 'off'} "
                    f"| {m['s']:.2f} | {split_cols} | {ratio:.3f} | "
                    f"{m['s'] / cycles_kept:.3f} | {verdict} |")
    table = ("| F12 of the unchanged scene | Persistent Data | s | export s | service job s "
             "| rest s | / Cycles | / Cycles persistent | floor (<= 0.15x Cycles) |\n"
             "|---|---|---:|---:|---:|---:|---:|---:|---|\n" + "\n".join(rows))
    print(table)
    load = os.getloadavg()
    body = "\n\n".join([
        "## A later F12 of an unchanged scene, Persistent Data off and on",
        f"Produced by `benchmarks/f12_persistent.py` (scene and rules in its docstring): six "
        f"smooth Suzannes at subdivision render level {level} on a ground ({triangles:,} "
        f"triangles), {WIDTH}x{HEIGHT}, {SPP} spp, the default Blackman-Harris 1.5 px "
        f"filter, service running; medians of {rounds} interleaved rounds after a warm-up. "
        f"Command: `.venv/bin/python {command}`; {os.cpu_count()} cores, load average "
        f"{load[0]:.2f} / {load[1]:.2f} at the end.",
        table,
        "```\n" + "\n".join(log) + "\n```",
    ])
    if not (args.no_docs or args.quick):
        write_section("f12-persistent", body)
    return 0 if met else 1


if __name__ == "__main__":
    raise SystemExit(main())
