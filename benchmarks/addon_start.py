"""How long the installed extension takes to start its service and render, per session.

    .venv/bin/python benchmarks/addon_start.py --python /tmp/bpy-only/bin/python
    .venv/bin/python benchmarks/addon_start.py --python P --zip build/x.zip --sessions 8

`--python` is an interpreter with only `bpy` installed (`python -m venv D && D/bin/pip
install bpy==5.0.1`), standing in for Blender. The first session installs the zip
(default: `scenesort addon-zip --platform linux-x64 --python X.Y` now, for that
Python's version) into a fresh Blender user
directory with an empty Warp kernel cache; each later session is a new process that
enables the installed extension, as a later Blender session does, with the kernel
cache the earlier ones filled. Each session times `bpy.ops.scenesort.server_start()`
until the health answer, then two Render AO of a plane and a sphere at 64x48.
Prints one JSON line per session; docs/addon.md has the numbers.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MODULE = "bl_ext.user_default.scenesort"

SESSION = f"""
import json, sys, time
import bpy, addon_utils
if sys.argv[2] == "install":
    result = bpy.ops.extensions.package_install_files(
        filepath=sys.argv[1], repo="user_default", enable_on_install=True)
    assert result == {{"FINISHED"}}, result
else:
    addon_utils.enable("{MODULE}", default_set=True)
for obj in list(bpy.data.objects):
    bpy.data.objects.remove(obj)
bpy.ops.mesh.primitive_plane_add(size=8)
bpy.ops.mesh.primitive_uv_sphere_add(radius=1, location=(0, 0, 1))
bpy.ops.object.camera_add(location=(0, -7, 4), rotation=(1.05, 0, 0))
scene = bpy.context.scene
scene.camera = bpy.context.object
scene.render.resolution_x, scene.render.resolution_y = 64, 48
scene.render.resolution_percentage = 100
times = [time.perf_counter()]
for op in (bpy.ops.scenesort.server_start, bpy.ops.scenesort.render_ao,
           bpy.ops.scenesort.render_ao):
    assert op() == {{"FINISHED"}}
    times.append(time.perf_counter())
addon_utils.disable("{MODULE}")
steps = [round(b - a, 2) for a, b in zip(times, times[1:])]
print(json.dumps(dict(zip(("start_s", "first_render_s", "second_render_s"), steps))))
"""


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--python", type=Path, required=True, help="a Python with only bpy")
    parser.add_argument("--zip", type=Path, help="the extension zip (default: build one)")
    parser.add_argument("--sessions", type=int, default=5, help="later sessions to time")
    args = parser.parse_args()
    python = args.python.absolute()  # not resolved: a venv's python is a link
    with tempfile.TemporaryDirectory(prefix="scenesort-start-") as tmp:
        work = Path(tmp)
        zip_path = args.zip or work / "scenesort-linux-x64.zip"
        if args.zip is None:  # the zip made for that Blender's Python
            version = subprocess.run(
                [str(python), "-c", "import sys; print('%d.%d' % sys.version_info[:2])"],
                capture_output=True, text=True, check=True,
            ).stdout.strip()  # fmt: skip
            subprocess.run(
                [sys.executable, "-m", "scenesort.backend.commands", "addon-zip", "--platform",
                 "linux-x64", "--python", version, "-o", str(zip_path)], cwd=ROOT, check=True,
            )  # fmt: skip
        env = {"PATH": "/usr/bin:/bin", "HOME": os.environ.get("HOME", tmp),
               "WARP_CACHE_PATH": str(work / "warp-cache")}  # fmt: skip
        env.update({f"BLENDER_USER_{d.upper()}": str(work / "user" / d)
                    for d in ("config", "scripts", "datafiles", "extensions")})  # fmt: skip
        for session in range(1 + args.sessions):
            phase = "install" if session == 0 else "later"
            proc = subprocess.run(
                [str(python), "-I", "-c", SESSION, str(zip_path), phase],
                cwd=work, env=env, capture_output=True, text=True, timeout=900,
            )  # fmt: skip
            if proc.returncode != 0:
                print(proc.stdout[-2000:], proc.stderr[-2000:], file=sys.stderr)
                return 1
            times = json.loads(proc.stdout.strip().splitlines()[-1])
            load = os.getloadavg()[0]
            print(json.dumps({"session": phase, **times, "load_average": round(load, 2)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
