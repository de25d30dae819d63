"""Esc during an F12 of a large scene, at each stage after the export: how soon Blender has
control back, in one headless Blender (bpy) session with a real service.

    .venv/bin/python benchmarks/esc.py [--triangles 3000000] [--rounds 3] [--no-docs]

The scene: one grid of about `--triangles` triangles under a camera, the BVH engine,
320x240 at 4096 spp (a job of minutes: Esc finds it running). Each round renders with an
engine whose Esc (`stopped()`, Blender's test_break) turns true at a stage's first step:
"uploading" (the body goes in chunks, each asking whether to go on), "building the BVH"
(one request, answered when the build is done: Esc does not wait for it), "running" (the
service's job, cancelled there). One vertex moves before each round, so that the scene is
new to the service and is uploaded and built again; each round waits for the service to
finish what it was doing before the next. Measured: from the first `stopped()` that
answered true to `render.render()` returning. Floor (issue 33): at most 0.5 s (medians).
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from pathlib import Path
from typing import ClassVar

HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != HERE]

import bpy  # noqa: E402  (before bmesh, which only bpy makes importable)

REPO = HERE.parent
sys.path.insert(0, str(REPO))

import bmesh  # noqa: E402

import addon  # noqa: E402
from addon import engine, prefs  # noqa: E402
from benchmarks.docs_section import write_section  # noqa: E402

FLOOR_S = 0.5
STAGES = {"upload": "uploading", "BVH build": "building the BVH", "job": "running"}


class Escaper(engine.AoEngine, bpy.types.RenderEngine):
    """The engine, with Esc pressed at the first step that starts with `stage`."""

    bl_idname = "SCENESORT_ESC_BENCH"
    bl_label = "scenesort AO (Esc at a stage)"
    bl_use_preview = False
    stage: ClassVar[str] = ""
    pressed: ClassVar[float | None] = None
    tasks: ClassVar[list] = []

    def stopped(self) -> bool:
        if self.task is not None and self.task not in Escaper.tasks:
            Escaper.tasks.append(self.task)
        if Escaper.pressed is None and self.task is not None and any(
                s.startswith(Escaper.stage) for s in self.task.steps):
            Escaper.pressed = time.perf_counter()
        return Escaper.pressed is not None


def build(triangles: int) -> bpy.types.Mesh:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon.register()
    bpy.utils.register_class(Escaper)
    scene = bpy.context.scene
    scene.world = bpy.data.worlds.new("World")
    scene.world.light_settings.distance = 0.5
    side = max(1, round(math.sqrt(triangles / 2)))
    mesh = bpy.data.meshes.new("Grid")
    bm = bmesh.new()
    bmesh.ops.create_grid(bm, x_segments=side, y_segments=side, size=4.0)
    bm.to_mesh(mesh)
    bm.free()
    scene.collection.objects.link(bpy.data.objects.new("Grid", mesh))
    cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    cam.location = (0.0, -6.0, 5.0)
    cam.rotation_euler = (math.radians(50), 0.0, 0.0)
    scene.collection.objects.link(cam)
    scene.camera = cam
    scene.render.resolution_x, scene.render.resolution_y = 320, 240
    scene.render.resolution_percentage = 100
    scene.scenesort.spp = 4096
    scene.render.engine = "SCENESORT"
    prefs.preferences(bpy.context).start_on_render = True
    return mesh


def escape_s(stage: str, mesh: bpy.types.Mesh, vertex: int) -> float:
    """Seconds from Esc at `stage` to F12's return, `vertex` moved first."""
    mesh.vertices[vertex].co.z += 1e-3  # a scene the service has not seen
    mesh.update()
    Escaper.stage, Escaper.pressed = STAGES[stage], None
    scene = bpy.context.scene
    scene.render.engine = Escaper.bl_idname
    try:
        bpy.ops.render.render()
        back = time.perf_counter()
    finally:
        scene.render.engine = "SCENESORT"
    if Escaper.pressed is None:
        raise SystemExit(f"the F12 ended before reaching '{STAGES[stage]}'")
    for task in Escaper.tasks:  # what Esc left running ends before the next round
        task.join(600)
    Escaper.tasks.clear()
    return back - Escaper.pressed


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--triangles", type=int, default=3_000_000)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--no-docs", action="store_true")
    args = parser.parse_args(argv)
    command = " ".join(["benchmarks/esc.py", *(argv if argv is not None else sys.argv[1:])])
    mesh = build(args.triangles)
    triangles = 2 * len(mesh.polygons)
    times: dict[str, list[float]] = {stage: [] for stage in STAGES}
    try:
        for r in range(args.rounds):
            for k, stage in enumerate(STAGES):
                times[stage].append(escape_s(stage, mesh, len(STAGES) * r + k))
            print(f"round {r}: " + ", ".join(f"{k} {v[-1]:.3f} s" for k, v in times.items()),
                  flush=True)
    finally:
        addon.unregister()
    rows, met = [], True
    for stage, values in times.items():
        med = statistics.median(values)
        met &= med <= FLOOR_S
        rows.append(f"| {stage} ('{STAGES[stage]}') | {med:.3f} s | {max(values):.3f} s | "
                    f"<= {FLOOR_S} s | {'met' if med <= FLOOR_S else 'NOT met'} |")
    table = ("| Esc during | median | worst | floor | |\n|---|---:|---:|---|---|\n"
             + "\n".join(rows))
    print(table)
    load = os.getloadavg()
    body = "\n\n".join([
        "## Esc during a large F12",
        f"Produced by `benchmarks/esc.py` (scene and rules in its docstring): a grid of "
        f"{triangles:,} triangles, from Esc at a stage's first step to F12's return; "
        f"{args.rounds} interleaved rounds. Command: `.venv/bin/python {command}`; "
        f"{os.cpu_count()} cores, load average {load[0]:.2f} at the end.",
        table,
    ])
    if not args.no_docs:
        write_section("esc", body)
    return 0 if met else 1


if __name__ == "__main__":
    raise SystemExit(main())
