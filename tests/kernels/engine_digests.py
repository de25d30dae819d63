"""Prints, as one JSON line, SHA-256 digests of the engine's answers on fixed inputs:
both BVH builders' nodes and orders, closest- and any-hit traces, both DACRT variants,
AO at fixed samples and to an error target, and a two-level scene. Run by
test_numpy_versions.py with numpy 1 (this project's venv) and numpy 2 (Blender 5.1+'s);
the engine must answer the same, bit for bit.

Usage: python engine_digests.py
"""

from __future__ import annotations

import hashlib
import json

import numpy as np
from scenesort.backend.render.scenes import shared_scene

from scenesort import kernels

WIDTH, HEIGHT = 96, 72


def digest(*arrays: np.ndarray) -> str:
    """Dtype, shape and bytes of each array, in order."""
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def depth_first(bvh: kernels.Bvh) -> tuple[np.ndarray, np.ndarray]:
    """The tree in depth-first order from the root, left child first (node boxes and
    counts, a leaf's first position in leaf order, -1 for inner nodes), and the leaf
    order: what the build decided, without inner nodes' child indices, which depend on
    the order in which the task pool's workers finish."""
    nodes = bvh.nodes()
    order, stack = [], [0]
    while stack:
        k = stack.pop()
        order.append(k)
        if nodes["count"][k] == 0:
            stack += [nodes["first"][k] + 1, nodes["first"][k]]
    picked = nodes[np.asarray(order)]
    picked["first"] = np.where(picked["count"] > 0, picked["first"], -1)
    return picked, bvh.permutation()


def tree(bvh: kernels.Bvh) -> str:
    """`depth_first`'s tree as a digest."""
    picked, permutation = depth_first(bvh)
    return digest(picked["lo"], picked["hi"], picked["count"], picked["first"], permutation)


def hits(h: kernels.Hits) -> str:
    return digest(h.t, h.triangle, h.u, h.v, h.instance)


def main() -> None:
    scene = shared_scene("bunny", WIDTH, HEIGHT)
    v, i = scene.vertices, scene.indices
    origins, directions, _, _ = scene.camera.rays()
    out = {"numpy": np.__version__}
    for method in ("median", "sah"):
        bvh = kernels.build_bvh(v, i, method=method, leaf_size=4)
        out[f"build {method}"] = tree(bvh)
        out[f"trace {method}"] = hits(kernels.trace(bvh, origins, directions))
        out[f"any-hit {method}"] = hits(kernels.trace(bvh, origins, directions, tmax=0.05,
                                                      any_hit=True))  # fmt: skip
    bvh = kernels.build_bvh(v, i)
    for variant in ("pool", "breadth_first"):
        out[f"dacrt {variant}"] = hits(kernels.dacrt_trace(v, i, origins, directions,
                                                           variant=variant))  # fmt: skip
    fixed = kernels.render_ao(bvh, origins, directions, spp=16, distance=0.05, seed=7)
    out["ao 16 spp"] = digest(fixed.ao, fixed.spp_used)
    target = kernels.render_ao(bvh, origins, directions, target_error=0.03, distance=0.05,
                               seed=7, image_shape=(HEIGHT, WIDTH))  # fmt: skip
    out["ao target 0.03"] = digest(target.ao, target.spp_used)
    angle = np.pi / 5
    turn = np.array([[np.cos(angle), -np.sin(angle), 0, 0.05],
                     [np.sin(angle), np.cos(angle), 0, 0], [0, 0, 1, 0]], np.float32)
    placed = np.stack([np.eye(3, 4, dtype=np.float32), turn])  # 3x4 object-to-world
    two = kernels.build_scene([bvh], np.zeros(2, np.int32), placed)
    out["scene trace"] = hits(kernels.trace(two, origins, directions))
    print(json.dumps(out))


if __name__ == "__main__":
    main()
