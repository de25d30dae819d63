"""F12 of an instanced scene after a small change, in one headless Blender (bpy) session
with a real service: what an artist pays after moving the camera or one object.

    .venv/bin/python benchmarks/f12_instances.py [--instances 400] [--rounds 3] [--quick]
        [--no-flat] [--no-docs]

The scene: a ground plane and `--instances` collection instances (on a jittered grid, each
turned) of a smooth UV sphere of 8,064 triangles: 3.2 M triangles flattened at 400.
320x240, 16 spp, the BVH engine. After a warm-up F12 (the service started, the meshes
sent and built), interleaved rounds of: an F12 of the unchanged scene, one after moving
the camera, one after moving one instance. Each F12's wall time (Blender's
`render.render()`), what it sent (mesh uploads) and built (mesh BVHs, top levels), from
the engine's own outcome. Then, once (`--no-flat` skips it), the same two changes with the
scene flattened, as every F12 did before instance lists were sent at F12.

Floor (issue 33): a frame after moving the camera or one object uploads and builds no mesh
and takes at most 1.5x the unchanged frame's time (medians).
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

import bpy  # noqa: E402  (before bmesh, which only bpy makes importable)
import numpy as np  # noqa: E402

REPO = HERE.parent
sys.path.insert(0, str(REPO))

import bmesh  # noqa: E402

import addon  # noqa: E402
from addon import export, pipeline, prefs  # noqa: E402
from benchmarks.docs_section import write_section  # noqa: E402

FLOOR_RATIO = 1.5
WIDTH, HEIGHT, SPP = 320, 240, 16


def build_scene(count: int) -> tuple[bpy.types.Object, bpy.types.Object]:
    """The ground, `count` collection instances of the sphere and a camera; (camera, one
    instance)."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon.register()
    scene = bpy.context.scene
    scene.world = bpy.data.worlds.new("World")
    scene.world.light_settings.distance = 1.0
    mesh = bpy.data.meshes.new("Sphere")
    bm = bmesh.new()
    bmesh.ops.create_uvsphere(bm, u_segments=64, v_segments=64, radius=0.45)
    for face in bm.faces:
        face.smooth = True
    bm.to_mesh(mesh)
    bm.free()
    asset = bpy.data.collections.new("Asset")  # not linked to the scene: only instanced
    asset.objects.link(bpy.data.objects.new("Sphere", mesh))
    side = math.ceil(math.sqrt(count))
    rng = np.random.default_rng(0)
    holders = []
    for k in range(count):
        holder = bpy.data.objects.new(f"Holder{k}", None)
        holder.instance_type, holder.instance_collection = "COLLECTION", asset
        i, j = divmod(k, side)
        holder.location = (i - side / 2 + rng.uniform(-0.2, 0.2),
                           j - side / 2 + rng.uniform(-0.2, 0.2), 0.5)
        holder.rotation_euler = tuple(rng.uniform(0, math.pi, 3))
        scene.collection.objects.link(holder)
        holders.append(holder)
    ground = bpy.data.meshes.new("Ground")
    s = side
    ground.from_pydata([(-s, -s, 0), (s, -s, 0), (s, s, 0), (-s, s, 0)], [], [(0, 1, 2, 3)])
    scene.collection.objects.link(bpy.data.objects.new("Ground", ground))
    cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    cam.location = (0.0, -0.9 * side, 0.55 * side)
    cam.rotation_euler = (math.radians(55), 0.0, 0.0)
    scene.collection.objects.link(cam)
    scene.camera = cam
    scene.render.resolution_x, scene.render.resolution_y = WIDTH, HEIGHT
    scene.render.resolution_percentage = 100
    scene.render.engine = "SCENESORT"
    scene.scenesort.spp = SPP
    prefs.preferences(bpy.context).start_on_render = True
    return cam, holders[len(holders) // 2]


def f12(outcomes: list) -> dict:
    """One F12: seconds, and what it sent and built (the engine's outcome)."""
    start = time.perf_counter()
    assert bpy.ops.render.render() == {"FINISHED"}
    seconds = time.perf_counter() - start
    out = outcomes[-1]
    report = out.build_report or {}
    uploads = sum(r.startswith(("PUT /v1/meshes", "POST /v1/scenes")) for r in out.requests)
    return {"s": seconds, "uploads": uploads, "built": len(report.get("built", [])),
            "top": report.get("top_level", "none"), "bytes": out.uploaded_bytes}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--instances", type=int, default=400)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="60 instances, 1 round, no flat")
    parser.add_argument("--no-flat", action="store_true", help="skip the flattened F12s")
    parser.add_argument("--no-docs", action="store_true", help="print only")
    args = parser.parse_args(argv)
    count, rounds = (60, 1) if args.quick else (args.instances, args.rounds)
    command = " ".join(["benchmarks/f12_instances.py", *(argv if argv is not None
                                                           else sys.argv[1:])])
    cam, one = build_scene(count)
    outcomes: list = []
    real = pipeline.render_job

    def spy(*a, **k):  # the real render, its outcome kept
        outcomes.append(real(*a, **k))
        return outcomes[-1]

    pipeline.render_job = spy
    try:
        flat_tris = export.export_scene(bpy.context.evaluated_depsgraph_get()).triangles
        warm = f12(outcomes)
        print(f"warm-up F12 (service start, meshes sent and built): {warm}", flush=True)
        runs: dict[str, list[dict]] = {"unchanged": [], "camera moved": [], "one object moved": []}
        for r in range(rounds):
            runs["unchanged"].append(f12(outcomes))
            cam.location.x += 0.05
            runs["camera moved"].append(f12(outcomes))
            one.location.x += 0.05
            runs["one object moved"].append(f12(outcomes))
            print(f"round {r}: " + ", ".join(f"{k} {v[-1]['s']:.2f} s" for k, v in runs.items()),
                  flush=True)
        flat: dict[str, dict] = {}
        if not (args.quick or args.no_flat):
            export.has_instances = lambda depsgraph: False  # every F12 before issue 33
            try:
                f12(outcomes)  # the flattened scene sent and built once
                cam.location.x += 0.05
                flat["camera moved"] = f12(outcomes)
                one.location.x += 0.05
                flat["one object moved"] = f12(outcomes)
            finally:
                del export.has_instances  # the module's own function again
    finally:
        pipeline.render_job = real
        addon.unregister()
    base = statistics.median(x["s"] for x in runs["unchanged"])
    rows, met = [], True
    for name, got in runs.items():
        med = statistics.median(x["s"] for x in got)
        sent = max(x["uploads"] for x in got)
        built = max(x["built"] for x in got)
        ok = name == "unchanged" or (sent == 0 and built == 0 and med <= FLOOR_RATIO * base)
        met &= ok
        flat_s = f"{flat[name]['s']:.2f}" if name in flat else "-"
        verdict = "" if name == "unchanged" else "met" if ok else "NOT met"
        rows.append(f"| {name} | {med:.2f} | {med / base:.2f} | {sent} | {built} | "
                    f"{got[-1]['top']} | {flat_s} | {verdict} |")
    table = ("| F12 | instance list s | / unchanged | meshes sent | mesh BVHs built | top level "
             "| flattened s | floor (<= 1.5x, nothing sent or built) |\n"
             "|---|---:|---:|---:|---:|---|---:|---|\n" + "\n".join(rows))
    print(table)
    load = os.getloadavg()
    body = "\n\n".join([
        "## F12 of an instanced scene after a small change",
        f"Produced by `benchmarks/f12_instances.py` (scene and rules in its docstring): "
        f"{count} collection instances of an 8,064-triangle smooth sphere on a ground "
        f"({flat_tris:,} triangles flattened), {WIDTH}x{HEIGHT}, {SPP} spp, the BVH engine, "
        f"service running; medians of {rounds} interleaved rounds after a warm-up. "
        f"Command: `.venv/bin/python {command}`; {os.cpu_count()} cores, load average "
        f"{load[0]:.2f} at the end.",
        table,
    ])
    if not (args.no_docs or args.quick):
        write_section("f12-instances", body)
    return 0 if met else 1


if __name__ == "__main__":
    raise SystemExit(main())
