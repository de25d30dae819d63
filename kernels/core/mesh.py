"""Triangle meshes on the device: which triangles have zero area.

Degenerate (zero-area) triangles are legal input: no ray hits them, so every engine leaves
them out; `degenerate_mask` finds them with the exact test of `triangle.is_degenerate`.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .launch import get_device, host_threads, launch_split, to_device
from .triangle import is_degenerate

wp.set_module_options({"enable_backward": False, "optimization_level": 3})


@wp.kernel
def degenerate_flags(vertices: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.vec3i),
                     out: wp.array(dtype=wp.int8)):
    f = indices[wp.tid()]
    out[wp.tid()] = wp.int8(wp.where(is_degenerate(vertices[f[0]], vertices[f[1]],
                                                   vertices[f[2]]), 1, 0))


def degenerate_mask(vertices: np.ndarray, indices: np.ndarray, device=None,
                    threads: int | None = None) -> np.ndarray:
    """Zero-area triangles of a validated mesh, as `build_bvh` skips them (the float64 cross
    product of the float32 edges is exactly zero): a bool mask, computed on every core."""
    device = get_device(device)
    m = len(indices)
    flags = np.empty(m, np.int8)
    out = to_device(flags, wp.int8, device)
    launch_split(degenerate_flags, m, [to_device(vertices, wp.vec3, device)],
                 [to_device(np.ascontiguousarray(indices, np.int32), wp.vec3i, device)], [],
                 [out], device, host_threads(device, threads))
    return (flags if device.is_cpu else out.numpy()).view(bool)


def count_degenerate(vertices: np.ndarray, indices: np.ndarray, device=None,
                     threads: int | None = None) -> int:
    """How many triangles `degenerate_mask` flags."""
    return int(np.count_nonzero(degenerate_mask(vertices, indices, device, threads)))
