"""A small subtree built by the native CPU code and by the Warp code (what CUDA runs) is the
same tree, bit for bit: rows, boxes and leaf order."""

from __future__ import annotations

import platform

import numpy as np
import pytest
import warp as wp
from hypothesis import given, settings
from hypothesis import strategies as st
from scenesort.kernels.bvh.build_data import METHOD_SAH, SMALL_TASK, BuildData, BuildItem
from scenesort.kernels.bvh.node import BvhNode
from scenesort.kernels.bvh.sweep_sah import subtree_rows, subtree_rows_native
from scenesort.kernels.core.compile_options import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)


@wp.kernel
def both_paths(native: BuildData, portable: BuildData, depth: int,
               made: wp.array(dtype=wp.vec2i)):
    made[0] = subtree_rows_native(native.items, native.subtree_nodes, 0, depth,
                                  native.max_depth, native.leaf_size, native.whole_max)
    made[1] = subtree_rows(portable, 0, depth)


def build_data(items: np.ndarray, root: np.ndarray, leaf_size: int, max_depth: int,
               whole_max: int) -> BuildData:
    b = BuildData()
    b.items = wp.array(items, dtype=BuildItem, device="cpu")
    b.spare = wp.zeros(len(items), dtype=BuildItem, device="cpu")
    rows = np.zeros(2 * int(SMALL_TASK) - 1, BvhNode.numpy_dtype())
    rows[0] = root
    b.subtree_nodes = wp.array(rows, dtype=BvhNode, device="cpu")
    b.method = int(METHOD_SAH)
    b.leaf_size = leaf_size
    b.max_depth = max_depth
    b.whole_max = whole_max
    return b


@pytest.mark.skipif(platform.machine() != "x86_64", reason="the native code is x86-64 only")
@settings(max_examples=80, deadline=None)
@given(count=st.integers(1, int(SMALL_TASK)), seed=st.integers(0, 2**32 - 1),
       grid=st.sampled_from([1, 4, 1024]), leaf_size=st.sampled_from([1, 2, 8]),
       max_depth=st.sampled_from([2, 5, 64]), whole_max=st.sampled_from([1, 3]))
def test_native_and_warp_subtrees_agree(count, seed, grid, leaf_size, max_depth, whole_max):
    """Coarse grids make ties of centroid keys and boxes that share a plane; signed zeros
    make min and max depend on the order they are taken in."""
    rng = np.random.default_rng(seed)
    lo = rng.integers(-grid, grid, (count, 3)) / grid
    hi = lo + rng.integers(0, 2, (count, 3)) / grid
    lo, hi = (np.where((x == 0) & (rng.random(x.shape) < 0.5), -0.0, x) for x in (lo, hi))
    items = np.zeros(count, BuildItem.numpy_dtype())
    items["lo"], items["hi"], items["tri"] = lo, hi, rng.permutation(count)
    root = np.zeros((), BvhNode.numpy_dtype())
    root["lo"], root["hi"] = lo.min(axis=0), hi.max(axis=0)
    root["first"], root["count"] = 0, count
    native = build_data(items, root, leaf_size, max_depth, whole_max)
    portable = build_data(items, root, leaf_size, max_depth, whole_max)
    made = wp.zeros(2, dtype=wp.vec2i, device="cpu")
    wp.launch(both_paths, dim=1, inputs=[native, portable, 3, made], device="cpu")
    (rows, deepest), (rows_warp, deepest_warp) = made.numpy()
    assert rows > 0, "the native code did not run on this CPU"
    assert (rows, deepest) == (rows_warp, deepest_warp)
    assert native.subtree_nodes.numpy()[:rows].tobytes() == \
        portable.subtree_nodes.numpy()[:rows].tobytes()
    assert native.items.numpy().tobytes() == portable.items.numpy().tobytes()
