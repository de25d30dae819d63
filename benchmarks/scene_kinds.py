"""Scenes of kinds the shared meshes do not cover, generated here (no downloads), for the
calibration of the error target (benchmarks/film_cost.py): a closed interior seen from
inside, thin geometry against the sky, the built-in scene (a room corner open to the sky)
and the same with depth of field. `scene_kind(name, width, height)` also takes a shared
scene's name."""

from __future__ import annotations

import dataclasses

import numpy as np
from scenesort.backend.render import scenes
from scenesort.backend.render.scenes import Scene
from scenesort.kernels.render.camera import Camera


def interior(width: int, height: int) -> Scene:
    """A closed room (6 x 8 x 3, every wall facing in) with boxes and spheres, the camera
    inside it: every camera ray hits, no pixel sees the sky."""
    lo, hi = np.array([-3.0, -4.0, 0.0]), np.array([3.0, 4.0, 3.0])
    x, y, z = np.diag(hi - lo)
    parts = [
        scenes._grid(lo, y, x, 48, 36),  # floor, facing up
        scenes._grid(hi, -x, -y, 36, 48),  # ceiling, facing down
        scenes._grid(lo, x, z, 36, 24),  # walls, facing the room
        scenes._grid(hi, -z, -x, 24, 36),
        scenes._grid(lo, z, y, 24, 48),
        scenes._grid(hi, -y, -z, 48, 24),
        scenes._box((-1.8, 2.6, 0.5), (1.0, 1.0, 1.0), 10.0, 8),
        scenes._box((1.9, 2.9, 0.9), (1.4, 0.6, 1.8), -5.0, 8),  # a cupboard by the wall
        scenes._box((0.4, 0.6, 0.4), (1.6, 0.9, 0.8), 30.0, 8),  # a low table
        scenes._icosphere((-1.2, -0.4, 0.45), 0.45, 4),
        scenes._icosphere((2.2, -1.5, 2.2), 0.35, 4),  # hanging in the air
    ]
    vertices, indices = scenes._merge(parts)
    camera = Camera.look_at((-2.4, -3.5, 1.7), (0.6, 1.5, 0.7), (0, 0, 1), 65.0, width, height)
    return _scene("interior", vertices, indices, camera)


def thin(width: int, height: int) -> Scene:
    """Grass blades (2 cm wide) and wires (1 cm thick) over a ground, seen against the sky:
    most covered pixels are edges."""
    rng = np.random.default_rng(7)
    parts = [scenes._grid((-6.0, -6.0, 0.0), (12.0, 0, 0), (0, 12.0, 0), 32, 32)]
    for x, y in rng.uniform(-3.0, 3.0, (400, 2)):
        tall = rng.uniform(0.3, 1.2)
        parts.append(scenes._box((x, y, tall / 2), (0.02, 0.004, tall), rng.uniform(0, 180), 1))
    for k in range(6):  # wires between two posts
        parts.append(scenes._box((0.0, 2.5 - k * 0.35, 1.0 + 0.06 * k), (7.0, 0.01, 0.01),
                                 0.0, 1))
    parts += [scenes._box((s * 3.5, 0.75, 1.0), (0.08, 0.08, 2.0), 0.0, 2) for s in (-1, 1)]
    vertices, indices = scenes._merge(parts)
    camera = Camera.look_at((0.0, -6.0, 1.4), (0.0, 1.0, 0.8), (0, 0, 1), 50.0, width, height)
    return _scene("thin", vertices, indices, camera)


def corner(width: int, height: int) -> Scene:
    """The built-in scene: a room corner open to the sky with a sphere, a torus and boxes."""
    return dataclasses.replace(scenes.default_scene(width, height), name="corner")


def depth_of_field(width: int, height: int) -> Scene:
    """The built-in scene through a wide aperture (f/0.2 at 50 mm: Cycles' aperture size
    lens / (2 f-stop)) focused on the sphere: most of the image is blurred."""
    scene = scenes.default_scene(width, height)
    cam = scene.camera
    sphere = np.array([0.2, 2.3, 1.2]) - np.asarray(cam.matrix_world)[:3, 3]
    focus = float(sphere @ cam.forward)  # camera-space depth
    camera = dataclasses.replace(cam, aperture_size=0.05 / (2 * 0.2), focus_distance=focus)
    return dataclasses.replace(scene, name="dof", camera=camera)


KINDS = {"interior": interior, "thin": thin, "corner": corner, "dof": depth_of_field}


def scene_kind(name: str, width: int, height: int) -> Scene:
    """A generated kind by name, else the shared scene of that name."""
    if name in KINDS:
        return KINDS[name](width, height)
    return scenes.shared_scene(name, width, height)


def _scene(name: str, vertices: np.ndarray, indices: np.ndarray, camera: Camera) -> Scene:
    return Scene(name, np.ascontiguousarray(vertices, np.float32),
                 np.ascontiguousarray(indices, np.int32), camera)

