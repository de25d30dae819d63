"""Run by tests/addon/test_extension_install.py in a Python that has only `bpy`.

Installs the extension zip with Blender's own installer into the (fresh) user
directory named by the BLENDER_USER_* variables, renders the scene below through the
add-on with its defaults (the panel's Render AO, then F12 with the engine into an EXR,
without and with Denoise, then Ctrl-F12 of two frames with the box moving), and writes
what the test compares to OUT_DIR: render.npz (the image's AO, the F12s' and frames' RGBA,
the exported triangles), render.json (camera, settings, how the service was started) and
the parity renders: F12 at PARITY_SPP and two Cycles AO passes at the same samples
(cycles_11.exr, cycles_12.exr, multilayer: the test reads them with OpenEXR, which this
Python does not have).
Usage: python install_and_render.py ZIP OUT_DIR
"""

from __future__ import annotations

import importlib
import json
import math
import os
import shutil
import sys
from pathlib import Path

import bpy
import numpy as np

MODULE = "bl_ext.user_default.scenesort"
WIDTH, HEIGHT = 32, 24
PARITY_SPP = 256
sys.path.insert(0, str(Path(__file__).parent))  # cycles_reference: only bpy and numpy


def _scene() -> bpy.types.Scene:
    """A floor with a box on it and a camera: occlusion in the corners where they meet."""
    for obj in list(bpy.data.objects):  # the factory startup's cube, light and camera
        bpy.data.objects.remove(obj)
    scene = bpy.context.scene
    floor = bpy.data.meshes.new("Floor")
    floor.from_pydata([(-4, -4, 0), (4, -4, 0), (4, 4, 0), (-4, 4, 0)], [], [(0, 1, 2, 3)])
    box = bpy.data.meshes.new("Box")
    h = 0.75
    verts = [(x, y, z) for z in (0, 2 * h) for y in (-h, h) for x in (-h, h)]
    faces = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    box.from_pydata(verts, [], faces)
    for name, data in (("Floor", floor), ("Box", box)):
        scene.collection.objects.link(bpy.data.objects.new(name, data))
    cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    scene.collection.objects.link(cam)
    cam.location, cam.rotation_euler = (0.0, -7.0, 4.0), (math.radians(60), 0.0, 0.0)
    scene.camera = cam
    scene.render.resolution_x, scene.render.resolution_y = WIDTH, HEIGHT
    scene.render.resolution_percentage = 100
    return scene


def _f12(scene: bpy.types.Scene, path: Path) -> np.ndarray:
    """F12 with the scenesort AO engine, written by Blender as a float EXR and read back:
    (H*W, 4) RGBA, top row first."""
    scene.render.engine = "SCENESORT"
    scene.render.film_transparent = True
    settings = scene.render.image_settings
    settings.file_format, settings.color_depth = "OPEN_EXR", "32"
    scene.render.filepath = str(path)
    scene.render.use_file_extension = False
    assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
    return _read(path)


def _read(path: Path) -> np.ndarray:
    """A float EXR Blender wrote, through bpy: (H*W, 4) RGBA, top row first."""
    img = bpy.data.images.load(str(path), check_existing=False)
    pixels = np.empty(len(img.pixels), dtype=np.float32)
    img.pixels.foreach_get(pixels)
    return pixels.reshape(HEIGHT, WIDTH, 4)[::-1].reshape(-1, 4)


def _ctrl_f12(scene: bpy.types.Scene, out: Path) -> np.ndarray:
    """Ctrl-F12 of frames 1-2, the box where it is on frame 1 and 1 unit along x on frame
    2, through Blender's own numbered output: (2, H*W, 4) RGBA."""
    box = bpy.data.objects["Box"]
    x = box.location.x
    box.keyframe_insert("location", frame=1)
    box.location.x = x + 1.0
    box.keyframe_insert("location", frame=2)
    scene.frame_start, scene.frame_end = 1, 2
    scene.render.filepath = str(out / "frame_")
    scene.render.use_file_extension = True
    try:
        assert bpy.ops.render.render(animation=True) == {"FINISHED"}
    finally:
        box.animation_data_clear()
        box.location.x = x
        scene.frame_set(1)
    return np.stack([_read(out / f"frame_{f:04d}.exr") for f in (1, 2)])


def _parity(scene: bpy.types.Scene, out: Path) -> np.ndarray:
    """F12 at PARITY_SPP with the World's AO distance, and Cycles' AO pass twice at the
    same samples and pixel filter (seeds 11 and 12) into OUT_DIR; F12's RGBA."""
    from cycles_reference import write_cycles_ao

    scene.scenesort.spp, scene.scenesort.ao_distance = PARITY_SPP, 0.0  # 0: the World's
    scene.world.light_settings.distance = 2.0
    film = (scene.cycles.pixel_filter_type, scene.cycles.filter_width)  # what F12 renders
    for seed in (11, 12):
        write_cycles_ao(scene, out / f"cycles_{seed}", PARITY_SPP, seed=seed, film=film)
    return _f12(scene, out / "parity.exr")


def main(zip_path: str, out_dir: str) -> None:
    import addon_utils  # only importable once bpy is

    out = Path(out_dir)
    assert shutil.which("scenesort") is None and "SCENESORT_COMMAND" not in os.environ
    result = bpy.ops.extensions.package_install_files(
        filepath=zip_path, repo="user_default", enable_on_install=True
    )
    assert result == {"FINISHED"}, result
    ext = importlib.import_module(MODULE)
    scene = _scene()
    scene.scenesort.spp, scene.scenesort.seed, scene.scenesort.ao_distance = 8, 3, 2.0
    try:
        assert bpy.ops.scenesort.render_ao() == {"FINISHED"}  # starts the service itself
        img = bpy.data.images["scenesort AO"]
        pixels = np.empty(len(img.pixels), dtype=np.float32)
        img.pixels.foreach_get(pixels)
        rgba = pixels.reshape(HEIGHT, WIDTH, 4)[::-1].reshape(-1, 4)  # top row first
        f12 = _f12(scene, out / "f12.exr")
        scene.scenesort.use_denoising = True  # the denoiser the zip bundles
        denoised = _f12(scene, out / "f12-denoised.exr")
        scene.scenesort.use_denoising = False
        frames = _ctrl_f12(scene, out)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        mesh = ext.export.export_scene(depsgraph)
        proc = ext.service._process
        status = bpy.context.window_manager.scenesort
        props = scene.scenesort
        info = {
            "camera": ext.camera.camera_dict(scene, depsgraph),
            "settings": {"spp": props.spp, "seed": props.seed, "distance": props.ao_distance,
                         "method": props.method, "leaf_size": props.leaf_size,
                         "film": list(ext.pipeline.film_filter(scene))},
            "argv": list(proc.args),
            "site_packages": str(ext.service.engine_root()),
            "url": status.url,
            "version": status.version,
            "python": sys.executable,
            "devices": ext.devices.found(),  # probed by the first render's start
        }  # fmt: skip
        parity = _parity(scene, out)  # last: it changes the samples and the distance
        np.savez(out / "render.npz", ao=rgba[:, 0], alpha=rgba[:, 3], f12=f12, denoised=denoised,
                 frames=frames, parity=parity, vertices=mesh.vertices,
                 indices=mesh.indices)  # fmt: skip
    finally:
        addon_utils.disable(MODULE)  # unregister: stops the service it started
    info["service_exit"] = proc.poll()
    (out / "render.json").write_text(json.dumps(info))


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
