"""Hair (Curves objects) and point clouds as triangles, the way AO meets them in Cycles.

Cycles traces curves as ribbons that face each ray (its default shape) or as round tubes
(Thick): either way a strand of radius r blocks a band about 2r wide seen from any
direction, which is what an AO ray meets. Here a strand is a tube of TUBE_SIDES sides
through its points, each point's radius (the `radius` attribute) the hexagon's
circumradius (widened to the circle's mean width it darkened the floor around a hair
patch more than Cycles does: tests/addon/test_strands.py), smooth-shaded with the tube's
radial normals. A point of a point cloud is a sphere of its radius (an icosphere of the
sphere's volume, smooth-shaded). Both become ordinary mesh arrays for the export
(`export._MeshArrays`): one mesh per object, in the object's space. All numpy, no
per-point Python. The points are joined by straight segments (Cycles' curves are smooth
between them), and a groom of 100k strands of 20 points becomes 23M triangles.
"""

from __future__ import annotations

from typing import Any

import numpy as np

TUBE_SIDES = 6  # a hexagonal cross-section: its silhouette is within 13% of the circle's
DEFAULT_RADIUS = 0.01  # Blender's, where a Curves or point cloud object has no radius
SPHERE_SUBDIVISIONS = 1  # an 80-triangle icosphere per point


def _attribute(data: Any, name: str, count: int, width: int, default: float) -> np.ndarray:
    """A point attribute as float64 (count, width) (or (count,)), or `default` without it."""
    found = data.attributes.get(name)
    if found is None or count == 0:
        return np.full((count, width) if width > 1 else count, default, np.float64)
    values = np.empty(count * width, np.float32)
    found.data.foreach_get("vector" if width > 1 else "value", values)
    return values.reshape(count, width).astype(np.float64) if width > 1 else (
        values.astype(np.float64))


def curve_tubes(curves: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A Curves datablock's strands as tubes: vertices (V, 3) float64, triangles (T, 3)
    int32 and their corner normals (T, 3, 3) float32 (radial: smooth)."""
    n = len(curves.points)
    offsets = np.empty(len(curves.curves) + 1, np.int32)
    curves.curve_offset_data.foreach_get("value", offsets)
    points = _attribute(curves, "position", n, 3, 0.0)
    radius = _attribute(curves, "radius", n, 1, DEFAULT_RADIUS)
    return tubes(points, radius, offsets)


def tubes(points: np.ndarray, radius: np.ndarray, offsets: np.ndarray,
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tubes through the curves whose points are points[offsets[k]:offsets[k + 1]]."""
    n, sides = len(points), TUBE_SIDES
    curve = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
    # the tangent at each point: along the curve (one-sided at its ends)
    ahead = np.minimum(np.arange(n) + 1, offsets[curve + 1] - 1)
    behind = np.maximum(np.arange(n) - 1, offsets[curve])
    tangent = points[ahead] - points[behind]
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-30)
    # one reference axis per curve (the one least along its overall direction), so that
    # the rings of a curve do not turn against each other
    direction = np.zeros((len(offsets) - 1, 3))
    np.add.at(direction, curve, np.abs(tangent))
    axis = np.eye(3)[np.argmin(direction, axis=1)][curve]
    u = np.cross(tangent, axis)
    u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-30)
    v = np.cross(tangent, u)
    angle = 2.0 * np.pi * np.arange(sides) / sides
    radial = (np.cos(angle)[None, :, None] * u[:, None, :]
              + np.sin(angle)[None, :, None] * v[:, None, :])  # (n, sides, 3)
    vertices = (points[:, None, :] + radius[:, None, None] * radial).reshape(-1, 3)
    # a segment joins point i to i + 1 of the same curve
    first = np.flatnonzero(curve[:-1] == curve[1:]) if n > 1 else np.zeros(0, np.int64)
    k = np.arange(sides)
    a = first[:, None] * sides + k  # ring i, side k
    b = first[:, None] * sides + (k + 1) % sides
    c, d = b + sides, a + sides  # ring i + 1
    triangles = np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, d], -1)],
                               axis=1).reshape(-1, 3).astype(np.int32)
    normals = radial.reshape(-1, 3)[triangles].astype(np.float32)
    return vertices, triangles, normals


def _icosphere() -> tuple[np.ndarray, np.ndarray]:
    """A unit icosphere: vertices on the sphere, outward triangles."""
    t = (1.0 + 5.0**0.5) / 2.0
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t),
         (0, 1, -t), (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
         (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8),
         (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    verts = [np.array(p, np.float64) / np.linalg.norm(p) for p in v]
    faces = [tuple(x) for x in f]
    for _ in range(SPHERE_SUBDIVISIONS):
        middle: dict[tuple[int, int], int] = {}
        faces = [g for a, b, c in faces for g in _split(verts, middle, a, b, c)]
    verts, faces = np.array(verts), np.array(faces, np.int32)
    # Scaled to the sphere's volume: the inscribed polyhedron holds 87% of it, and blocks
    # that much less of the rays around it (measured against Cycles' spheres).
    corners = verts[faces]
    volume = abs(np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1],
                                                               corners[:, 2]))).sum() / 6.0
    return verts * (4.0 / 3.0 * np.pi / volume) ** (1.0 / 3.0), faces


def _split(verts: list, middle: dict, a: int, b: int, c: int) -> list[tuple[int, int, int]]:
    """Triangle (a, b, c) as four, its edges' midpoints pushed onto the sphere (each made
    once per subdivision, `middle`)."""
    def mid(i: int, j: int) -> int:
        key = (min(i, j), max(i, j))
        if key not in middle:
            p = verts[i] + verts[j]
            verts.append(p / np.linalg.norm(p))
            middle[key] = len(verts) - 1
        return middle[key]

    ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
    return [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]


_SPHERE = _icosphere()


def point_spheres(cloud: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A point cloud's points as spheres of their radius: vertices, triangles and the
    spheres' own normals as corner normals (smooth), as `curve_tubes`."""
    n = len(cloud.points)
    centres = _attribute(cloud, "position", n, 3, 0.0)
    radius = _attribute(cloud, "radius", n, 1, DEFAULT_RADIUS)
    unit, faces = _SPHERE
    vertices = (centres[:, None, :] + radius[:, None, None] * unit[None]).reshape(-1, 3)
    triangles = (faces[None] + (len(unit) * np.arange(n))[:, None, None]).reshape(-1, 3)
    directions = unit[faces] / np.linalg.norm(unit[faces], axis=-1, keepdims=True)
    normals = np.tile(directions.astype(np.float32), (n, 1, 1))
    return vertices, triangles.astype(np.int32), normals
