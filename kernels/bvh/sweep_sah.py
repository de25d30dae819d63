"""Small SAH subtrees built in one worker by exact sweeps over sorted ranges.

SAH nodes of at most SMALL_TASK triangles are not pool tasks: the worker that makes one
builds its subtree in place, where the pool's phases would cost more than the work.
"""

from __future__ import annotations

import warp as wp

from ..core.atomics import shared_add, shared_max
from ..core.box import INF, half_area, longest_axis, max3, min3
from .build_data import (
    MAX_DEPTH,
    METHOD_SAH,
    NODE_COUNT,
    SMALL_TASK,
    BuildData,
    BuildItem,
    SmallFloats,
    SmallInts,
    write_node,
    write_node_box,
)

# sort_small on a CPU, as native code: the same insertion sort, its pairs on the stack
# without the zero-filling of Warp's local vectors (512 bytes a sort, 2.5M sorts of 7 items
# on average at 4M triangles), the items moved through the spare array as before. (CUDA:
# 0, the Warp code runs.)
SORT_SOURCE = """
#if !defined(__CUDA_ARCH__)
    float keys[SMALL];
    int order[SMALL];
    auto* it = items.data;
    for (int i = 0; i < count; ++i) {
        const float key = it[start + i].lo.c[axis] + it[start + i].hi.c[axis];
        int j = i;
        while (j > 0 && !(keys[j - 1] <= key)) {
            keys[j] = keys[j - 1];
            order[j] = order[j - 1];
            --j;
        }
        keys[j] = key;
        order[j] = start + i;
    }
    auto* out = spare.data;
    for (int i = 0; i < count; ++i)
        out[start + i] = it[order[i]];
    for (int i = start; i < start + count; ++i)
        it[i] = out[i];
    return 1;
#else
    return 0;
#endif
""".replace("SMALL", str(int(SMALL_TASK)))


@wp.func_native(SORT_SOURCE)
def sort_small_native(items: wp.array(dtype=BuildItem), spare: wp.array(dtype=BuildItem),
                      start: int, count: int, axis: int) -> int:
    """sort_small's sort (SORT_SOURCE); 0 where not compiled."""
    ...


@wp.func
def sort_small(b: BuildData, start: int, count: int, axis: int):
    """Sort a small range by centroid on `axis`: an insertion sort of (key, position) pairs
    held locally, then one pass through Swap's spare array (free here: the range is this
    worker's) to move the items."""
    if sort_small_native(b.items, b.spare, start, count, axis) != 0:
        return
    keys = SmallFloats()
    order = SmallInts()
    for i in range(count):
        it = b.items[start + i]
        key = it.lo[axis] + it.hi[axis]
        j = i
        while j > 0:
            if keys[j - 1] <= key:
                break
            keys[j] = keys[j - 1]
            order[j] = order[j - 1]
            j -= 1
        keys[j] = key
        order[j] = start + i
    for i in range(count):
        src = order[i]
        b.spare[start + i] = b.items[src]
    for i in range(start, start + count):
        b.items[i] = b.spare[i]


@wp.func
def small_split(b: BuildData, start: int, count: int, area: float, may_leaf: bool) -> int:
    """Exact SAH over the count - 1 planes of a sorted small range: the size of the left
    part, or 0 where a leaf is allowed and cheaper (traversal and intersection cost 1)."""
    right_area = SmallFloats()
    lo = wp.vec3(INF)
    hi = wp.vec3(-INF)
    for k in range(count - 1, 0, -1):  # right_area[k]: items k .. count - 1
        it = b.items[start + k]
        lo = min3(lo, it.lo)
        hi = max3(hi, it.hi)
        right_area[k] = half_area(lo, hi)
    best = wp.where(may_leaf, area * float(count), INF)
    best_k = int(0)
    lo = wp.vec3(INF)
    hi = wp.vec3(-INF)
    for k in range(1, count):
        it = b.items[start + k - 1]
        lo = min3(lo, it.lo)
        hi = max3(hi, it.hi)
        cost = area + half_area(lo, hi) * float(k) + right_area[k] * float(count - k)
        if cost < best:
            best = cost
            best_k = k
    return best_k


@wp.func
def range_box(b: BuildData, start: int, count: int) -> wp.mat33:
    """Rows: the box of a range's triangles and its centroids' extent."""
    lo = wp.vec3(INF)
    hi = wp.vec3(-INF)
    clo = wp.vec3(INF)
    chi = wp.vec3(-INF)
    for i in range(start, start + count):
        it = b.items[i]
        lo = min3(lo, it.lo)
        hi = max3(hi, it.hi)
        c = it.lo + it.hi  # twice the centroid: only the longest axis matters
        clo = min3(clo, c)
        chi = max3(chi, c)
    return wp.matrix_from_rows(lo, hi, chi - clo)


@wp.func
def centroid_axis(extent: wp.vec3) -> int:
    """The longest axis of a centroid box's extent, or -1 where the centroids coincide."""
    axis = longest_axis(wp.vec3(0.0), extent)
    return wp.where(extent[axis] > 0.0, axis, -1)


@wp.func
def small_subtree(b: BuildData, node: int, depth: int):
    """Finish the subtree of a node written as a leaf. SAH: a range of at most SMALL_TASK
    triangles is built here, in the worker that made it, where the pool's phases would cost
    more than the work: each node is sorted on its longest centroid axis (unless its parent
    already sorted it so) and cut at the exact SAH minimum over all count - 1 planes, and
    becomes a leaf wherever that is cheaper (leaf_size is then a maximum, as in Embree).
    Median: the node stays a leaf."""
    if b.method != METHOD_SAH:
        return
    n = b.nodes[node]
    nodes = SmallInts()  # the stack: node, depth, split axis, axis the range is sorted by
    depths = SmallInts()
    axes = SmallInts()
    sorted_by = SmallInts()
    nodes[0] = node
    depths[0] = depth
    axes[0] = centroid_axis(range_box(b, n.first, n.count)[2])
    sorted_by[0] = -1
    sp = int(1)
    deepest = depth
    while sp > 0:
        sp -= 1
        n = b.nodes[nodes[sp]]
        d = depths[sp]
        axis = axes[sp]
        deepest = wp.max(deepest, d)
        if n.count < 2 or d >= b.max_depth - 1:
            continue
        k = n.count / 2  # coincident centroids: halve, as the pool's tasks do
        if axis >= 0:
            if sorted_by[sp] != axis:
                sort_small(b, n.first, n.count, axis)
            k = small_split(b, n.first, n.count, half_area(n.lo, n.hi),
                            n.count <= b.leaf_size)
        elif n.count <= b.leaf_size:
            k = 0
        if k == 0:
            continue
        left = shared_add(b.counters, NODE_COUNT, 2)
        write_node(b, nodes[sp], n.lo, n.hi, left, 0)
        lbox = range_box(b, n.first, k)
        rbox = range_box(b, n.first + k, n.count - k)
        write_node_box(b, left, lbox, n.first, k)
        write_node_box(b, left + 1, rbox, n.first + k, n.count - k)
        nodes[sp] = left
        axes[sp] = centroid_axis(lbox[2])
        nodes[sp + 1] = left + 1
        axes[sp + 1] = centroid_axis(rbox[2])
        for c in range(2):
            depths[sp + c] = d + 1
            sorted_by[sp + c] = axis
        sp += 2
    shared_max(b.counters, MAX_DEPTH, deepest)
