"""Headless Blender (the `bpy` module) with the add-on imported as the package `addon`.

`registered` gives each test a fresh empty scene with the add-on registered, and
unregisters it afterwards (which also stops any service it started).
"""

from __future__ import annotations

import socket
import sys
from collections.abc import Iterator
from pathlib import Path

import bpy
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import addon  # noqa: E402 - needs the repo root on sys.path

# Blender's own extension validator, shipped inside the bpy wheel.
BLENDER_EXT = Path(bpy.utils.system_resource("SCRIPTS")) / "addons_core/bl_pkg/cli/blender_ext.py"


@pytest.fixture
def registered() -> Iterator[bpy.types.Scene]:
    """An empty scene (factory settings, no objects) with the add-on registered."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon.register()
    try:
        yield bpy.context.scene
    finally:
        addon.unregister()


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
