"""Blender's Bake (types Ambient Occlusion and Normal) with the scenesort engine.

Blender hands `RenderEngine.bake` a result whose BakePrimitive pass holds, per texel, two
barycentric weights and then the loop triangle of the baked object's evaluated mesh (an
int32's bits in a float32, -1 where no triangle covers the texel; bpy 4.2-5.3, read
headless); the same for image textures
and colour attributes (one texel per face corner). Those become points of the flattened
render scene's triangles (`export.Span`), which a service surface job shades as a camera
render would its primary hits (`kernels.surface_ao`: the front side, the shading normals,
the terminator offset, samples and error target); the AO goes back as Combined, and
Blender applies the margin and writes the target, as it does for Cycles.

Blender's weights (a, b) belong to the loop triangle's first and second corners (Cycles'
`init_from_bake` turns them into its own u = b, v = 1 - a - b); the engine's (u, v) belong
to the second and third corners.
"""

from __future__ import annotations

import numpy as np

from .export import SceneMesh, Span

PASS = "AO"
# Normal needs no service: the engine hands Blender world-space shading normals and
# Blender turns them into the panel's space (tangent, object, world) and swizzle, as it
# does for Cycles' (object_bake_api's RE_bake_normal_world_to_*).
NORMAL = "NORMAL"


def refusal(pass_type: str) -> str | None:
    """Why the engine does not bake `pass_type` (None: it does)."""
    if pass_type in (PASS, NORMAL):
        return None
    name = pass_type.replace("_", " ").title()
    return (f"scenesort AO bakes Ambient Occlusion and Normal only, not {name}: choose "
            "one of those, or Cycles for the other passes")


def bent_normal_materials(obj) -> list[str]:  # noqa: ANN001 - a bpy.types.Object
    """The names of `obj`'s materials whose nodes bend the shading normal (a link into a
    Normal input: Bump, Normal Map): Cycles' Normal bake applies those, this one does not."""
    return [slot.material.name for slot in obj.material_slots
            if slot.material is not None and slot.material.node_tree is not None
            and any(link.to_socket.name == "Normal" for link in slot.material.node_tree.links)]


def texel_points(primitive: np.ndarray, span: Span) -> tuple[np.ndarray, ...]:
    """From the BakePrimitive pass ((texels, 3) float32) of an object whose loop triangles
    are `span` in the flattened scene: the covered texels' indices and their points as
    the engine takes them (scene triangle, u, v)."""
    ids = np.ascontiguousarray(primitive[:, 2]).view(np.int32)
    texels = np.flatnonzero(ids >= 0)
    local = ids[texels]
    if len(local) and int(local.max()) >= span.count:
        raise ValueError(f"Blender's bake names loop triangle {int(local.max())}, but the "
                         f"object rendered {span.count}: bake again after a scene update")
    a = primitive[texels, 0].astype(np.float64)
    b = primitive[texels, 1].astype(np.float64)
    c = np.clip(1.0 - a - b, 0.0, 1.0)  # the third corner's weight
    # Mirrored objects reach the scene with each triangle's corners reversed.
    u, v = (b, a) if span.mirrored else (b, c)
    return (texels.astype(np.int32), (span.first + local).astype(np.int32),
            u.astype(np.float32), v.astype(np.float32))


def texel_normals(mesh: SceneMesh, triangles: np.ndarray, u: np.ndarray,
                  v: np.ndarray) -> np.ndarray:
    """World-space unit shading normals ((texels, 3) float32) at the points `texel_points`
    gives: smooth triangles' corner normals interpolated, flat ones' geometric normal (the
    scene's corner order keeps it outward on mirrored objects too)."""
    corners = mesh.vertices[mesh.indices[triangles]].astype(np.float64)
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    if mesh.normals is not None:
        w = np.stack([1.0 - u - v, u, v], 1).astype(np.float64)[:, :, None]
        smooth_corners = mesh.normals[triangles].astype(np.float64)
        smooth = np.abs(smooth_corners).sum(axis=(1, 2)) > 0.0  # zero corners: flat
        normal[smooth] = (w[smooth] * smooth_corners[smooth]).sum(axis=1)
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    return (normal / np.where(length > 0.0, length, 1.0)).astype(np.float32)


def combined(values: np.ndarray, texels: np.ndarray, count: int) -> np.ndarray:
    """The Combined pass Blender copies into the target: AO ((texels,)) as grey or
    normals ((texels, 3)) as RGB, alpha 1, on the covered texels; 0 elsewhere (Blender's
    margin fills from the covered ones)."""
    rgba = np.zeros((count, 4), np.float32)
    values = np.asarray(values, np.float32)
    rgba[texels, :3] = values[:, None] if values.ndim == 1 else values
    rgba[texels, 3] = 1.0
    return rgba
