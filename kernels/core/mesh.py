"""Triangle meshes on the device, made once per scene and reused by every call.

`DeviceMesh` holds a validated mesh (numpy) and its vertex and index arrays on the device;
what a tracer derives from it is computed on first use and kept: the triangles that have
an area (degenerate ones are legal input that no ray hits, so every engine leaves them
out) and the triangles by id with their boxes (what DACRT reads). A `Bvh` keeps the mesh
it was built from, so AO and DACRT on the same scene upload nothing again. Shading normals
(`Shading`) are kept beside it the same way, once per set of normals.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .box import max3, min3
from .claim import Claims, claimed_arg, claimed_items, launch_claimed
from .compile_options import MODULE_OPTIONS
from .launch import get_device, host_threads
from .triangle import is_degenerate
from .validate import as_shading, as_triangle_mesh

wp.set_module_options(MODULE_OPTIONS)


@wp.struct
class Shading:
    """Per-corner shading normals of a mesh on the device (what Blender renders with).

    normals: three unit `vec3` per triangle id, corner by corner (zero corners: flat);
    offsets: per triangle, Cycles' shadow terminator geometry offset (0: none);
    smooth: 0 when the mesh has no shading normals (the arrays then hold one dummy entry:
    a kernel argument cannot be None), 1 otherwise.
    """

    normals: wp.array(dtype=wp.vec3)
    offsets: wp.array(dtype=float)
    smooth: int


@wp.func
def triangle_corners(vertices: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.vec3i),
                     i: int) -> wp.mat33:
    """Rows: the three vertices of triangle i."""
    f = indices[i]
    return wp.matrix_from_rows(vertices[f[0]], vertices[f[1]], vertices[f[2]])


@wp.kernel
def degenerate_flags(vertices: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.vec3i),
                     out: wp.array(dtype=wp.int8), claims: Claims):
    items = claimed_items(claims, wp.tid())
    for i in range(items[0], items[1]):
        t = triangle_corners(vertices, indices, i)
        out[i] = wp.int8(wp.where(is_degenerate(t[0], t[1], t[2]), 1, 0))


@wp.kernel
def triangle_soup(
    vertices: wp.array(dtype=wp.vec3),
    indices: wp.array(dtype=wp.vec3i),
    tri_verts: wp.array(dtype=wp.vec3),
    tri_lo: wp.array(dtype=wp.vec3),
    tri_hi: wp.array(dtype=wp.vec3),
):
    """Per triangle id: its three vertices one after the other, and its box."""
    i = wp.tid()
    t = triangle_corners(vertices, indices, i)
    tri_verts[3 * i] = t[0]
    tri_verts[3 * i + 1] = t[1]
    tri_verts[3 * i + 2] = t[2]
    tri_lo[i] = min3(min3(t[0], t[1]), t[2])
    tri_hi[i] = max3(max3(t[0], t[1]), t[2])


def degenerate_mask(vertices: np.ndarray, indices: np.ndarray, device=None,
                    threads: int | None = None) -> np.ndarray:
    """Zero-area triangles of a validated mesh, as `build_bvh` skips them (the float64 cross
    product of the float32 edges is exactly zero): a bool mask, computed on every core."""
    device = get_device(device)
    m = len(indices)
    flags = np.empty(m, np.int8)
    out = claimed_arg(flags, wp.int8, device)
    launch_claimed(degenerate_flags, m, [
        claimed_arg(vertices, wp.vec3, device),
        claimed_arg(np.ascontiguousarray(indices, np.int32), wp.vec3i, device), out],
        device, host_threads(device, threads))
    return (flags if device.is_cpu else out.numpy()).view(bool)


def count_degenerate(vertices: np.ndarray, indices: np.ndarray, device=None,
                     threads: int | None = None) -> int:
    """How many triangles `degenerate_mask` flags."""
    return int(np.count_nonzero(degenerate_mask(vertices, indices, device, threads)))


def _same(a, b) -> bool:
    """Whether two shading inputs are the same: equal numbers, else the same object (arrays
    are taken as read-only: one changed in place is not seen)."""
    numbers = (int, float, np.number)
    if isinstance(a, numbers) and isinstance(b, numbers):
        return float(a) == float(b)
    return a is b


class DeviceMesh:
    """A validated triangle mesh and its arrays on one device.

    vertices, indices: the validated numpy arrays ((N, 3) float32, (M, 3) int32).
    v, f: the same on the device (`wp.vec3`, `wp.vec3i`).
    """

    def __init__(self, vertices, indices, device=None, *, validated: bool = False):
        self.device = get_device(device)
        if not validated:  # `validated`: the caller passed as_triangle_mesh's output
            vertices, indices = as_triangle_mesh(vertices, indices)
        self.vertices, self.indices = vertices, indices
        # on the CPU the numpy arrays themselves, read as the caller's arrays are (unchanged
        # while the mesh is in use): a copy of them took 18 bytes a triangle of a build
        copy = not self.device.is_cpu
        self.v = wp.array(vertices, dtype=wp.vec3, device=self.device, copy=copy)
        self.f = wp.array(indices, dtype=wp.vec3i, device=self.device, copy=copy)
        self._valid_ids: np.ndarray | None = None
        self._soup: tuple[wp.array, wp.array, wp.array] | None = None
        # ((normals, terminator_offset) as the caller passed them, the device struct)
        self._shading: tuple[tuple, Shading] | None = None

    def valid_ids(self) -> np.ndarray:
        """The ids of the triangles with an area (int32, ascending), found once."""
        if self._valid_ids is None:
            mask = degenerate_mask(self.vertices, self.indices, "cpu")
            self._valid_ids = np.flatnonzero(~mask).astype(np.int32)
        return self._valid_ids

    def soup(self) -> tuple[wp.array, wp.array, wp.array]:
        """(tri_verts, tri_lo, tri_hi): every triangle's vertices (three `vec3` per id) and
        box, made on the device once."""
        if self._soup is None:
            m = len(self.indices)
            soup = (wp.empty(max(3 * m, 1), dtype=wp.vec3, device=self.device),
                    wp.empty(max(m, 1), dtype=wp.vec3, device=self.device),
                    wp.empty(max(m, 1), dtype=wp.vec3, device=self.device))
            if m:
                wp.launch(triangle_soup, dim=m, inputs=[self.v, self.f, *soup],
                          device=self.device)
            self._soup = soup
        return self._soup

    def shading(self, normals, terminator_offset) -> Shading:
        """The device copy of `validate.as_shading(normals, terminator_offset)`: made for
        the first call with these objects and kept, so renders with the same arrays (a
        service's cached scene) neither validate nor upload them again."""
        key = (normals, terminator_offset)
        cached = self._shading
        if cached is not None and all(_same(a, b) for a, b in zip(cached[0], key, strict=True)):
            return cached[1]
        shading = as_shading(normals, terminator_offset, len(self.indices))
        out = Shading()
        out.smooth = int(shading is not None)
        corners, offsets = shading or (np.zeros((1, 3), np.float32), np.zeros(1, np.float32))
        out.normals = wp.array(corners.reshape(-1, 3), dtype=wp.vec3, device=self.device)
        out.offsets = wp.array(offsets, dtype=float, device=self.device)
        self._shading = (key, out)
        return out

    @property
    def nbytes(self) -> int:
        """Device bytes held: the vertex and index arrays and what was derived from them."""
        arrays = [self.v, self.f, *(self._soup or ())]
        if self._shading is not None:
            arrays += [self._shading[1].normals, self._shading[1].offsets]
        return sum(a.capacity for a in arrays)


WARP_MODULES = (triangle_soup.module,)  # this module's kernels (see core.launch.load_modules)
