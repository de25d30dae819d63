"""Blender's memory while the add-on exports a large scene for F12, against the upload's
size, in one headless Blender (bpy) process.

    .venv/bin/python benchmarks/export_memory.py [--triangles 3000000] [--no-docs]

Scenes of about `--triangles` triangles each: one flat grid; the same grid smooth (its
corner normals go too: 36 more bytes a triangle); 400 objects of their own meshes; 100
linked duplicates of one mesh (flattened, so each is placed in the scene's arrays). For
each, in a fresh scene with its depsgraph evaluated: the process's peak resident memory
(Linux VmHWM, reset first) above what it held before, over what F12 does before the
upload (`export.export_scene`, then the content hash over its blocks), and the upload's
size; also numpy's own peak (tracemalloc), which leaves out Blender's caches (its loop
triangles, made on the first read). Floor (issue 33): peak growth at most 1.5x the
upload.
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import math
import os
import sys
import tracemalloc
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != HERE]

import bpy  # noqa: E402  (before bmesh, which only bpy makes importable)

REPO = HERE.parent
sys.path.insert(0, str(REPO))

import bmesh  # noqa: E402

from addon import client, export  # noqa: E402
from benchmarks.docs_section import write_section  # noqa: E402
from benchmarks.scale import reset_peak, rss_kib  # noqa: E402

FLOOR = 1.5
LIBC = ctypes.CDLL("libc.so.6")


def grid(name: str, triangles: int, smooth: bool = False) -> bpy.types.Mesh:
    side = max(1, round(math.sqrt(triangles / 2)))
    mesh = bpy.data.meshes.new(name)
    bm = bmesh.new()
    bmesh.ops.create_grid(bm, x_segments=side, y_segments=side, size=2.0)
    for face in bm.faces:
        face.smooth = smooth
    bm.to_mesh(mesh)
    bm.free()
    return mesh


def scene_of(kind: str, triangles: int) -> None:
    """A fresh scene of `kind`, its objects linked."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    objects = bpy.context.scene.collection.objects
    if kind in ("one grid, flat", "one grid, smooth"):
        objects.link(bpy.data.objects.new("Grid", grid("Grid", triangles, "smooth" in kind)))
    elif kind == "400 objects":
        for k in range(400):
            obj = bpy.data.objects.new(f"Grid{k}", grid(f"Grid{k}", triangles // 400))
            obj.location = (k % 20 * 2.5, k // 20 * 2.5, 0.0)
            objects.link(obj)
    else:  # linked duplicates
        shared = grid("Shared", triangles // 100)
        for k in range(100):
            obj = bpy.data.objects.new(f"Copy{k}", shared)
            obj.location = (k % 10 * 2.5, k // 10 * 2.5, 0.0)
            obj.rotation_euler.z = 0.1 * k
            objects.link(obj)


def measure(kind: str, triangles: int) -> dict:
    scene_of(kind, triangles)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    gc.collect()
    LIBC.malloc_trim(0)  # what making the scene freed goes back: growth is new memory
    before = rss_kib("VmRSS")
    reset_peak()
    tracemalloc.start()
    mesh = export.export_scene(depsgraph)
    client.scene_id(len(mesh.vertices), mesh.triangles, mesh.blocks())
    traced = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    peak = rss_kib("VmHWM")
    upload = mesh.nbytes
    row = {"kind": kind, "triangles": mesh.triangles, "upload_mb": upload / 2**20,
           "peak_mb": (peak - before) / 1024, "traced_mb": traced / 2**20}
    row["ratio"], row["traced_ratio"] = row["peak_mb"] / row["upload_mb"], traced / upload
    del mesh
    gc.collect()
    return row


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--triangles", type=int, default=3_000_000)
    parser.add_argument("--no-docs", action="store_true")
    args = parser.parse_args(argv)
    command = " ".join(["benchmarks/export_memory.py",
                        *(argv if argv is not None else sys.argv[1:])])
    kinds = ("one grid, flat", "one grid, smooth", "400 objects", "100 linked duplicates")
    rows = [measure(kind, args.triangles) for kind in kinds]
    met = all(r["ratio"] <= FLOOR for r in rows)
    lines = ["| scene | triangles | upload | peak growth (RSS) | ratio | numpy's peak | ratio "
             "| floor |", "|---|---:|---:|---:|---:|---:|---:|---|"]
    lines += [f"| {r['kind']} | {r['triangles']:,} | {r['upload_mb']:.0f} MB | "
              f"{r['peak_mb']:.0f} MB | {r['ratio']:.2f} | {r['traced_mb']:.0f} MB | "
              f"{r['traced_ratio']:.2f} | {'met' if r['ratio'] <= FLOOR else 'NOT met'} |"
              for r in rows]
    table = "\n".join(lines)
    print(table)
    body = "\n\n".join([
        "## Blender's memory during a large export",
        f"Produced by `benchmarks/export_memory.py` (scenes and rules in its docstring): "
        f"peak resident growth of the Blender process over the export and the content "
        f"hash, against the upload's size; floor {FLOOR}x. Command: `.venv/bin/python "
        f"{command}`; {os.cpu_count()} cores.",
        table,
    ])
    if not args.no_docs:
        write_section("export-memory", body)
    return 0 if met else 1


if __name__ == "__main__":
    raise SystemExit(main())
