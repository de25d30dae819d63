"""Culling before any BVH: which instances of a list may change a pixel of a camera's AO
image, decided from the meshes' object boxes (`cull.mesh_box`, kept per mesh under
`box_key`) under the transforms (the placement, kept per list under `placement_key`) and
the AO distance (the request's, else the scene default over all instances, culled ones too,
as `render_ao` computes it from the culled scene's bounds)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scenesort.backend.wire import binary as wire
from scenesort.backend.work.store import Store


def placement_key(scene_id: str) -> str:
    """The cache key of an instance list's placement (`place_instances`) and its meshes'
    largest triangle sides: what culling needs of it, whatever the camera."""
    return f"{scene_id}/placed"


def box_key(mesh_id: str) -> str:
    """The cache key of a mesh's object box and largest triangle side (`cull.mesh_box`)."""
    return f"{mesh_id}/box"


@dataclass(frozen=True)
class View:
    """What a camera render sees: the framed camera, the AO distance (None: the scene
    default) and how many pixels outside the image its camera rays start (a pixel
    filter's reach, `film.filter_reach`)."""

    camera: Any
    distance: float | None
    reach: float = 0.0


def placement(store: Store, scene: wire.InstanceScene) -> tuple[Any, np.ndarray]:
    """The instance list's placement (`place_instances`, which `build_scene` then reuses)
    from the meshes' boxes, before any BVH, and the meshes' largest triangle sides. Both
    depend on the list alone: kept under `placement_key`."""
    from scenesort.kernels.render.cull import mesh_box
    from scenesort.kernels.scene.api import place_instances

    kept = store.get(placement_key(scene.scene_id))
    if kept is None:
        found = []
        for mesh in scene.meshes:
            box = store.get(box_key(mesh.scene_id))
            if box is None:
                box = mesh_box(mesh.vertices, mesh.indices)
                store.put(box_key(mesh.scene_id), box, 64)
            found.append(box)
        placed = place_instances(np.stack([b for b, _ in found]), scene.mesh_index,
                                 scene.transforms)
        kept = placed, np.array([e for _, e in found])
        held = [placed.lo, placed.hi, placed.mesh_ids, placed.transforms, *placed.frames.values()]
        store.put(placement_key(scene.scene_id), kept, sum(a.nbytes for a in held))
    return kept


def visible(store: Store, scene: wire.InstanceScene, view: View) -> tuple[np.ndarray, Any]:
    """The instances that may change a pixel of the view's AO image (`cull.
    visible_instances`), decided from the meshes' boxes before any BVH is made, and their
    `placement`: a camera-only change pays the planes' test only."""
    from scenesort.kernels.render import default_distance
    from scenesort.kernels.render.cull import visible_instances

    placed, extents = placement(store, scene)
    # The scene default over every instance: render_ao's from the culled scene's bounds,
    # which are the placement's (build_scene counts the culled instances' boxes).
    distance = default_distance(placed) if view.distance is None else view.distance
    return visible_instances(placed, extents, view.camera, distance, view.reach), placed
