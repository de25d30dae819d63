"""Scenes, cameras and renders for the add-on tests in headless Blender (`bpy`). Helpers
live here, not in conftest.py, so that test modules import them by a name no other test
folder uses."""

from __future__ import annotations

import math
import socket
from pathlib import Path

import bpy
import numpy as np

REPO = Path(__file__).resolve().parents[2]
# Blender's own extension validator, shipped inside the bpy wheel.
BLENDER_EXT = Path(bpy.utils.system_resource("SCRIPTS")) / "addons_core/bl_pkg/cli/blender_ext.py"


def free_port() -> int:
    """A TCP port nothing listens on right now (the OS picks it)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def box_mesh(name: str, size: float = 2.0) -> bpy.types.Mesh:
    """A closed cube mesh (6 quads, 12 triangles) centred on the origin."""
    import bmesh  # only importable once bpy is

    mesh = bpy.data.meshes.new(name)
    bm = bmesh.new()
    bmesh.ops.create_cube(bm, size=size)
    bm.to_mesh(mesh)
    bm.free()
    return mesh


def grid_mesh(name: str, n: int, size: float) -> bpy.types.Mesh:
    """An n x n grid of quads in the z=0 plane: a floor with 2*n*n triangles."""
    xs = np.linspace(-size / 2, size / 2, n + 1)
    verts = [(x, y, 0.0) for y in xs for x in xs]
    faces = [
        (j * (n + 1) + i, j * (n + 1) + i + 1, (j + 1) * (n + 1) + i + 1, (j + 1) * (n + 1) + i)
        for j in range(n)
        for i in range(n)
    ]
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(verts, [], faces)
    return mesh


def plane_mesh(name: str, size: float) -> bpy.types.Mesh:
    """A square in the z=0 plane (2 triangles)."""
    h = size / 2
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata([(-h, -h, 0), (h, -h, 0), (h, h, 0), (-h, h, 0)], [], [(0, 1, 2, 3)])
    return mesh


def add_object(
    scene: bpy.types.Scene, name: str, data: bpy.types.ID | None, location=(0.0, 0.0, 0.0)
) -> bpy.types.Object:
    obj = bpy.data.objects.new(name, data)
    obj.location = location
    scene.collection.objects.link(obj)
    return obj


def add_camera(
    scene: bpy.types.Scene, location, rotation, width: int = 64, height: int = 48
) -> bpy.types.Object:
    cam = add_object(scene, "Camera", bpy.data.cameras.new("Camera"), location)
    cam.rotation_euler = rotation
    scene.camera = cam
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    return cam


def render_with_engine(scene: bpy.types.Scene, ao_distance: float, spp: int, seed: int,
                       transparent: bool = True) -> None:
    """F12 by the scenesort engine (which starts its service) into 32-bit EXRs, with a
    World of AO distance `ao_distance`, as a judge against Cycles needs it."""
    import addon.prefs

    scene.world = bpy.data.worlds.new("World")
    scene.world.light_settings.distance = ao_distance
    scene.scenesort.spp, scene.scenesort.seed = spp, seed
    # F12 renders through the scene's pixel filter: the pixel-centre one of the Cycles judge
    scene.cycles.pixel_filter_type, scene.cycles.filter_width = "GAUSSIAN", 0.01
    scene.render.engine = "SCENESORT"
    scene.render.film_transparent = transparent
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    addon.prefs.preferences(bpy.context).start_on_render = True


def read_image(path: Path) -> np.ndarray:
    """An image file's RGBA, (height, width, 4), row 0 at the top."""
    img = bpy.data.images.load(str(path))
    try:
        pixels = np.empty(len(img.pixels), np.float32)
        img.pixels.foreach_get(pixels)
        return pixels.reshape(img.size[1], img.size[0], 4)[::-1]
    finally:
        bpy.data.images.remove(img)


def f12(scene: bpy.types.Scene, path: Path) -> np.ndarray:
    """F12 and save: the EXR Blender wrote, its RGBA (row 0 at the top)."""
    scene.render.filepath = str(path)
    assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
    return read_image(path.with_suffix(".exr"))


def shading(mesh) -> dict:  # noqa: ANN001 - an export.SceneMesh
    """`kernels.render_ao`'s normal arguments for an exported scene (none when it is flat)."""
    pairs = (("normals", mesh.normals), ("terminator_offset", mesh.terminator_offsets))
    return {name: value for name, value in pairs if value is not None}


def direct_film(scene: bpy.types.Scene, mesh, cam: dict,  # noqa: ANN001 - a SceneMesh
                **settings) -> tuple[np.ndarray, np.ndarray]:
    """What F12 asks the service for, from the engine itself (no add-on, no service):
    `kernels.render_film` of the exported `mesh` and `cam` (`camera.camera_dict`) with the
    panel's samples, BVH and AO distance, the scene's pixel filter (pixel centres where the
    options fall back, as the service does) and the mesh's normals; `settings` override
    any of these (`normals=None`: flat). AO (a miss counts 1) and coverage, (H, W)."""
    from scenesort.kernels import AoOptions, Camera

    from addon import pipeline
    from scenesort import kernels

    props = scene.scenesort
    bvh = kernels.build_bvh(mesh.vertices, mesh.indices, method=props.method,
                            leaf_size=props.leaf_size, device="cpu")
    pixel_filter, filter_width = pipeline.film_filter(scene)
    shading_args = shading(mesh)  # render_film's keywords for the geometry's normals
    for name in ("normals", "terminator_offset"):
        if name in settings:
            shading_args[name] = settings.pop(name)
    options = AoOptions(spp=props.spp, seed=props.seed, distance=pipeline.ao_distance(scene),
                        denoise=props.use_denoising, pixel_filter=pixel_filter,
                        filter_width=filter_width).with_(**settings)
    if options.film_fallback is not None:  # the service's rule (backend/render/camera_render)
        options = options.with_(filter_width=0.0)
    film = kernels.render_film(bvh, Camera.from_dict(cam), options, **shading_args)
    return film.ao, film.alpha


def ao_pass(ao: np.ndarray, coverage: np.ndarray) -> np.ndarray:
    """Cycles' AO pass of a job's AO (a miss counts 1) and coverage: the hits' samples,
    as the add-on writes it (addon/image.py)."""
    return np.maximum(ao + coverage - 1.0, 0.0)


def ctrl_f12(scene: bpy.types.Scene, folder: Path, first: int = 1, last: int = 3) -> list:
    """Ctrl-F12 of frames first..last into `folder` as PNGs (the scene's 32-bit EXR output
    is set again afterwards): the files Blender numbered, as PIL images in frame order."""
    from PIL import Image

    settings = scene.render.image_settings
    scene.frame_start, scene.frame_end = first, last
    scene.render.filepath = str(folder / "frame_")
    settings.file_format = "PNG"
    try:
        assert bpy.ops.render.render(animation=True) == {"FINISHED"}
    finally:
        settings.file_format, settings.color_depth = "OPEN_EXR", "32"
    names = sorted(p.name for p in folder.iterdir())
    assert names == [f"frame_{f:04d}.png" for f in range(first, last + 1)]
    return [Image.open(folder / name) for name in names]


FRAMES = (1, 2, 3, 4)  # animated_scene's: the blob deforms from 1 to 3 and holds on 4


def animated_scene(scene: bpy.types.Scene) -> bpy.types.Scene:
    """A floor; one cube mesh under three objects, one of them moving and one mirrored,
    and in a collection instance; a grid deformed by an animated shape key; a moving camera."""
    add_object(scene, "Floor", grid_mesh("Floor", 4, 8.0))
    cube = box_mesh("Cube", 1.0)
    for i in range(3):
        add_object(scene, f"Cube{i}", cube, (2.0 * i - 2.0, 0.0, 0.5))
    bpy.data.objects["Cube2"].scale = (-1.0, 1.0, 2.0)  # mirrored, non-uniform
    mover = bpy.data.objects["Cube1"]
    mover.keyframe_insert("location", frame=1)
    mover.location.z = 2.0
    mover.keyframe_insert("location", frame=3)
    blob = add_object(scene, "Blob", grid_mesh("Blob", 3, 1.0), (0.0, 2.0, 1.0))
    blob.shape_key_add(name="Basis")
    key = blob.shape_key_add(name="Up")
    for point in key.data:
        point.co.z += 0.3 * point.co.x
    key.value = 0.0
    key.keyframe_insert("value", frame=1)
    key.value = 1.0
    key.keyframe_insert("value", frame=3)
    parts = bpy.data.collections.new("Parts")
    parts.objects.link(bpy.data.objects.new("Part", cube))
    empty = add_object(scene, "Instancer", None, (0.0, -2.0, 0.0))
    empty.instance_type, empty.instance_collection = "COLLECTION", parts
    cam = add_camera(scene, (0.0, -8.0, 4.0), (math.radians(60), 0.0, 0.0), 32, 24)
    cam.keyframe_insert("location", frame=1)
    cam.location.x = 1.0
    cam.keyframe_insert("location", frame=4)
    scene.frame_start, scene.frame_end = FRAMES[0], FRAMES[-1]
    scene.scenesort.spp, scene.scenesort.seed, scene.scenesort.ao_distance = 4, 3, 1.5
    scene.frame_set(2)
    return scene


def bake_target(obj: bpy.types.Object, size: int,
                image: bpy.types.Image | None = None) -> bpy.types.Image:
    """`image`, or a float image filled with -1 so that texels no triangle covers stay -1
    (bake with use_clear=False, margin 0), in an active Image Texture node of the object's
    only material."""
    if image is None:
        image = bpy.data.images.new(f"{obj.name} bake", size, size, float_buffer=True)
        image.pixels.foreach_set(np.full(size * size * 4, -1.0, np.float32))
    material = bpy.data.materials.new(obj.name)
    if material.node_tree is None:  # Blender 4.x; 5.x materials always have nodes
        material.use_nodes = True
    node = material.node_tree.nodes.new("ShaderNodeTexImage")
    node.image = image
    material.node_tree.nodes.active = node
    obj.data.materials.clear()
    obj.data.materials.append(material)
    return image


def uv_sphere_mesh(name: str, segments: int, rings: int, smooth: bool) -> bpy.types.Mesh:
    """A UV sphere of radius 1 with its texture coordinates (a UV map named UVMap)."""
    import bmesh  # only importable once bpy is

    mesh = bpy.data.meshes.new(name)
    bm = bmesh.new()
    bm.loops.layers.uv.new("UVMap")
    bmesh.ops.create_uvsphere(bm, u_segments=segments, v_segments=rings, radius=1.0,
                              calc_uvs=True)  # fmt: skip
    bm.to_mesh(mesh)
    bm.free()
    if smooth:
        mesh.shade_smooth()
    return mesh
