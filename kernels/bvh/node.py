"""The BVH's layout in memory: 32-byte nodes in one flat array, and the device view that
traversal kernels read (Output of the build, 2012 paper, sec. 4.2), which also carries the
wide nodes collapsed from them (bvh.wide)."""

from __future__ import annotations

import numpy as np
import warp as wp


@wp.struct
class BvhNode:
    """32 bytes. Inner nodes: children at `first` and `first + 1`, `count` 0."""

    lo: wp.vec3  # 12 bytes
    first: int  # 4: leaf: first triangle position in leaf order; inner: left child index
    hi: wp.vec3  # 12
    count: int  # 4: leaf: triangles (> 0); inner: 0


@wp.struct
class BvhArrays:
    nodes: wp.array(dtype=BvhNode)
    # v0, v1, v2 per triangle in leaf order, for the binary traversal's leaves only (CUDA,
    # width 2): a CPU wide tree's leaves are its blocks, and one entry stands in
    tri_verts: wp.array(dtype=wp.vec3)
    tri_ids: wp.array(dtype=int)  # the caller's triangle index per leaf position
    # the mesh (DeviceMesh.v, .f): finish_hit's triangle, and what the collapse and the
    # refit fill the leaves from
    vertices: wp.array(dtype=wp.vec3)
    indices: wp.array(dtype=wp.vec3i)
    wide: wp.array(dtype=float)  # width 4 or 8: the wide nodes (layout in bvh.wide) ...
    blocks: wp.array(dtype=float)  # ... and their leaves' triangle blocks
    width: int  # 2: traverse `nodes`; 4 or 8: traverse `wide`


def empty_root(device) -> wp.array:
    """The BVH of a mesh with no triangles: a root whose box, a point at infinity, no ray
    enters (an inverted box would look like all of space to the slab test)."""
    node = np.zeros(1, dtype=BvhNode.numpy_dtype())
    node["lo"] = np.inf
    node["hi"] = np.inf
    return wp.array(node, dtype=BvhNode, device=device)


SAH_BLOCK = 1 << 20  # nodes per block of sah_cost: its float temporaries stay a few MB


def sah_cost(nodes: np.ndarray) -> float:
    """SAH cost with traversal and intersection cost 1: sum over nodes of A(node)/A(root)
    times 1 for inner nodes and times the triangle count for leaves. Summed in blocks of
    SAH_BLOCK nodes: over all of them at once, the temporaries took 20 bytes per triangle
    at the top of a build's memory."""
    raw = np.ascontiguousarray(nodes).view(np.float32).reshape(len(nodes), 8)  # 32-byte rows
    count = raw.view(np.int32)[:, 7]
    total = 0.0
    root = 0.0
    for first in range(0, len(raw), SAH_BLOCK):
        rows = raw[first: first + SAH_BLOCK]
        e = np.maximum(rows[:, 4:7] - rows[:, 0:3], np.float32(0.0))
        area = e[:, 0] * e[:, 1] + e[:, 1] * e[:, 2] + e[:, 2] * e[:, 0]  # float32: a statistic
        if first == 0:
            root = float(area[0])
            if root <= 0:
                return float(count[0]) if len(nodes) == 1 else float(len(nodes))
        # a sum, not np.dot: after a BLAS call over this many nodes OpenBLAS's threads spin
        # for 0.1 s or more, taking a core from whatever the caller runs next (the next
        # build's workers, a trace's threads)
        terms = area.astype(np.float64) * np.maximum(count[first: first + SAH_BLOCK], 1)
        total += float(terms.sum())
    return total / root
