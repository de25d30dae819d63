"""What a camera's AO image cannot depend on: geometry outside the view volume widened by the
AO distance.

A pixel's value depends on its primary ray's closest hit p, which lies in the camera's view
volume (inside the image's edges, between clip_start and clip_end), and on occlusion rays
from p (pushed off the surface by a few ulps, lifted toward the smooth surface by at most
twice the triangle's diameter) no longer than the AO distance. So a box that lies more than
distance + lift + rounding outside one plane of the view volume can change no pixel: the
view volume widened by a ball of that radius lies inside the six half-spaces pushed out by
it. Such instances are left out of the top level (`build_scene(visible=...)`), such
triangles out of a single mesh's BVH; the image is the same (tests/kernels/render/
test_cull.py). Valid for the camera's own rays (`Camera.rays()`), and with `reach` for rays
from raster points up to that many pixels outside the image (a pixel filter's samples:
film.filter_reach).

Whole instances, not triangles, are culled in two-level scenes: a mesh's BVH would become
camera-dependent and a camera-only change would have to rebuild it, while the top level is
rebuilt every frame anyway (cheap: one box per instance). The decision needs no BVH
(`mesh_box` of the mesh data, `scene.place_instances`), so backend/frames.py makes it
first and builds only the meshes of the instances in view. Triangle culling
(`visible_triangles`) is for a single mesh far larger than the view, rendered from one
camera (a still): its BVH is built once for that camera.
"""

from __future__ import annotations

import numpy as np

from ..core.mesh import degenerate_mask
from ..core.validate import as_triangle_mesh
from ..scene.api import Placement
from .camera import Camera

ROUNDING = 1e-5  # of the scene's and camera's largest coordinate: spawn offsets, float32
DISTANCE_MARGIN = 1e-3  # relative, on the AO distance


def view_planes(camera: Camera, reach: float = 0.0) -> np.ndarray:
    """(6, 4) float64 rows (n, b), |n| = 1: the view volume is where n . p + b >= 0 for all
    six (left, right, bottom, top, near, far), p in world space; its sides `reach` pixels
    outside the image's edges."""
    corners = camera.raster_to_camera(np.array([-reach, camera.width + reach]),
                                      np.array([camera.height + reach, -reach]))
    (xa, ya, _), (xb, yb, _) = corners  # left-bottom and right-top of the image
    cs, ce = camera.clip_start, camera.clip_end
    if camera.type == "PERSP":  # through the eye: x >= xa depth, depth = -z
        rows = [(1, 0, xa, 0), (-1, 0, -xb, 0), (0, 1, ya, 0), (0, -1, -yb, 0)]
    else:
        rows = [(1, 0, 0, -xa), (-1, 0, 0, xb), (0, 1, 0, -ya), (0, -1, 0, yb)]
    rows += [(0, 0, -1, -cs), (0, 0, 1, ce)]
    planes = np.array(rows, np.float64)
    planes /= np.linalg.norm(planes[:, :3], axis=1, keepdims=True)
    r, c = camera.rotation, camera.position
    normals = planes[:, :3] @ r.T  # n . R^T (p - c) = (R n) . p - (R n) . c
    return np.column_stack([normals, planes[:, 3] - normals @ c])


def boxes_outside(lo: np.ndarray, hi: np.ndarray, planes: np.ndarray,
                  margin: np.ndarray) -> np.ndarray:
    """Boxes (N, 3) that lie farther than `margin` (N,) outside some plane."""
    mid = 0.5 * (lo.astype(np.float64) + hi)
    half = 0.5 * (hi.astype(np.float64) - lo)
    reach = mid @ planes[:, :3].T + half @ np.abs(planes[:, :3]).T + planes[:, 3]  # (N, 6)
    return (reach < -margin[:, None]).any(axis=1)


def _margin(distance: float, lift: np.ndarray, *coords: np.ndarray) -> np.ndarray:
    if not float(distance) > 0:
        raise ValueError(f"distance must be > 0 (the render's AO distance), got {distance!r}")
    scale = max(float(np.abs(c[np.isfinite(c)]).max(initial=0.0)) for c in coords)
    return float(distance) * (1.0 + DISTANCE_MARGIN) + lift + ROUNDING * scale


def mesh_box(vertices: np.ndarray, indices: np.ndarray) -> tuple[np.ndarray, float]:
    """A mesh's object box, (2, 3) float32 over its triangles with an area (the `bounds`
    `build_bvh` gives it; empty: +inf, -inf), and the largest side of their boxes (the lift
    bound's triangle size): what `place_instances` and `visible_instances` need of a mesh,
    from its data alone (no BVH built)."""
    vertices, indices = as_triangle_mesh(vertices, indices)
    keep = indices[~degenerate_mask(vertices, indices, "cpu")]
    if not len(keep):
        return np.array([[np.inf] * 3, [-np.inf] * 3], np.float32), 0.0
    # Per coordinate, corner arrays apart: numpy's reductions over short axes are 10x slower.
    box, extent = np.empty((2, 3), np.float32), 0.0
    for axis in range(3):
        a, b, c = (vertices[keep[:, k], axis] for k in range(3))
        low, high = np.minimum(np.minimum(a, b), c), np.maximum(np.maximum(a, b), c)
        box[0, axis], box[1, axis] = low.min(), high.max()
        extent = max(extent, float((high - low).max()))
    return box, extent


def visible_instances(placed: Placement, extents: np.ndarray, camera: Camera,
                      distance: float, reach: float = 0.0) -> np.ndarray:
    """(I,) bool: the placed instances (`place_instances`, from the meshes' boxes) whose
    geometry may change a pixel of the camera's AO image with this AO distance; `extents`
    (K,): each mesh's largest triangle box side (`mesh_box`). The others may be left out
    (`build_scene(visible=...)`), and a mesh none of the visible ones uses left unbuilt.
    `reach`: camera rays start up to this many pixels outside the image (`view_planes`)."""
    planes = view_planes(camera, reach)
    norm = np.abs(placed.frames["lin"]).sum(axis=2).max(axis=1)  # ||M||_inf per instance
    lift = 2.0 * np.sqrt(3.0) * norm * np.asarray(extents, np.float64)[placed.mesh_ids]
    lo, hi = placed.lo, placed.hi
    margin = _margin(distance, lift, lo, hi, camera.position)
    return placed.valid & ~boxes_outside(lo, hi, planes, margin)


def visible_triangles(vertices: np.ndarray, indices: np.ndarray, camera: Camera,
                      distance: float) -> np.ndarray:
    """(M,) bool: a single mesh's triangles that may change a pixel of the camera's AO image
    with this AO distance (build the BVH of these alone for that camera)."""
    corners = np.asarray(vertices, np.float32)[np.asarray(indices)]  # (M, 3, 3)
    lo, hi = corners.min(axis=1), corners.max(axis=1)
    lift = 2.0 * np.sqrt(3.0) * float((hi - lo).max(initial=0.0))
    margin = _margin(distance, np.full(len(lo), lift), lo, hi, camera.position)
    return ~boxes_outside(lo, hi, planes=view_planes(camera), margin=margin)
