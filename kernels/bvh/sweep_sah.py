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
    SUBTREE_NODES,
    BuildData,
    BuildItem,
    SmallFloats,
    SmallInts,
    write_node,
    write_node_box,
)
from .node import BvhNode

# subtree_rows on a CPU, as native code: the same tree as the Warp code (the same float32
# operations, stack order and rows), with the range loaded once into local 4-float boxes
# and twice-centroids and sorted as a permutation of them, and the items written back once,
# in leaf order, at the end (the Warp code moves them through the spare array at every sort
# and reads them twice more per node for the children's boxes). The left child's boxes are
# the prefix sweep's at the cut; the right child's are taken again in item order, as
# range_box takes them (in the suffix sweep's order a box with 0.0 and -0.0 bounds keeps
# the other zero). Returns (rows made, deepest depth), or (0, 0) where the Warp code runs:
# CUDA, and a range over SMALL_TASK (a leaf by the depth cap).
SUBTREE_SOURCE = """
#if defined(__x86_64__) && !defined(__CUDA_ARCH__)
    typedef float f4 __attribute__((vector_size(4 * sizeof(float))));
    constexpr int N = SMALL;
    const float inf = __builtin_inff();
    const f4 up = {inf, inf, inf, inf}, down = -up;
    // minps(x, y) is x < y ? x : y, maxps(x, y) x > y ? x : y: core.box's min3 / max3
    auto lower = [](f4 x, f4 y) { return __builtin_ia32_minps(x, y); };
    auto upper = [](f4 x, f4 y) { return __builtin_ia32_maxps(x, y); };
    auto half_area = [](f4 l, f4 h) {  // core.box.half_area
        const f4 e = h - l;
        const float x = e[0] > 0.0f ? e[0] : 0.0f, y = e[1] > 0.0f ? e[1] : 0.0f,
                    z = e[2] > 0.0f ? e[2] : 0.0f;
        return x * y + y * z + z * x;
    };
    auto axis_of = [](f4 clo, f4 chi) {  // centroid_axis
        const f4 e = chi - clo;
        int a = 0;
        if (e[1] > e[a]) a = 1;
        if (e[2] > e[a]) a = 2;
        return e[a] > 0.0f ? a : -1;
    };
    auto* row = nodes.data + rows;  // row 0: the subtree's root, a leaf over the range
    const int start = row[0].first, total = row[0].count;
    if (total > N)  // a leaf by the depth cap: the Warp code keeps it so
        return wp::vec2i(0, 0);
    auto* it = items.data + start;
    __typeof__(*it) item[N];  // the range as it came, and per item its box and twice its centroid
    f4 lo[N], hi[N], c[N];
    int perm[N];  // position i of the range holds item perm[i]
    f4 clo = up, chi = down;
    for (int i = 0; i < total; ++i) {
        item[i] = it[i];
        lo[i] = (f4){it[i].lo.c[0], it[i].lo.c[1], it[i].lo.c[2], 0.0f};
        hi[i] = (f4){it[i].hi.c[0], it[i].hi.c[1], it[i].hi.c[2], 0.0f};
        c[i] = lo[i] + hi[i];
        clo = lower(clo, c[i]);
        chi = upper(chi, c[i]);
        perm[i] = i;
    }
    int st_row[N], st_depth[N], st_axis[N], st_sorted[N];  // the stack, as subtree_rows'
    st_row[0] = 0;
    st_depth[0] = depth;
    st_axis[0] = axis_of(clo, chi);
    st_sorted[0] = -1;
    float keys[N], right_area[N];
    int order[N];
    int sp = 1, made = 1, deepest = depth;
    while (sp > 0) {
        --sp;
        const int r = st_row[sp], d = st_depth[sp], axis = st_axis[sp];
        deepest = d > deepest ? d : deepest;
        const int count = row[r].count;
        int* p = perm + (row[r].first - start);
        if (count <= whole_max || d >= max_depth - 1)
            continue;
        int k = count / 2;  // coincident centroids: halve
        f4 llo = up, lhi = down, lclo = up, lchi = down;  // the left child's boxes
        bool swept = false;  // the left child's boxes are the sweep's at the cut
        if (axis >= 0) {
            if (st_sorted[sp] != axis) {  // sort_small: a stable insertion sort
                for (int i = 0; i < count; ++i) {
                    const float key = c[p[i]][axis];
                    int j = i;
                    while (j > 0 && !(keys[j - 1] <= key)) {
                        keys[j] = keys[j - 1];
                        order[j] = order[j - 1];
                        --j;
                    }
                    keys[j] = key;
                    order[j] = p[i];
                }
                for (int i = 0; i < count; ++i)
                    p[i] = order[i];
            }
            f4 bl = up, bh = down;  // small_split's sweeps
            for (int j = count - 1; j > 0; --j) {
                bl = lower(bl, lo[p[j]]);
                bh = upper(bh, hi[p[j]]);
                right_area[j] = half_area(bl, bh);
            }
            const f4 nlo = {row[r].lo.c[0], row[r].lo.c[1], row[r].lo.c[2], 0.0f};
            const f4 nhi = {row[r].hi.c[0], row[r].hi.c[1], row[r].hi.c[2], 0.0f};
            const float area = half_area(nlo, nhi);
            float best = count <= leaf_size ? area * (float)count : inf;
            k = 0;
            swept = true;
            bl = up, bh = down;
            f4 bcl = up, bch = down;
            for (int j = 1; j < count; ++j) {
                bl = lower(bl, lo[p[j - 1]]);
                bh = upper(bh, hi[p[j - 1]]);
                bcl = lower(bcl, c[p[j - 1]]);
                bch = upper(bch, c[p[j - 1]]);
                const float cost = area + half_area(bl, bh) * (float)j
                                   + right_area[j] * (float)(count - j);
                if (cost < best) {
                    best = cost;
                    k = j;
                    llo = bl, lhi = bh, lclo = bcl, lchi = bch;
                }
            }
        } else if (count <= leaf_size) {
            k = 0;
        }
        if (k == 0)
            continue;
        f4 rlo = up, rhi = down, rclo = up, rchi = down;  // range_box of each child
        for (int j = swept ? k : 0; j < count; ++j) {
            f4& l = j < k ? llo : rlo;
            f4& h = j < k ? lhi : rhi;
            f4& cl = j < k ? lclo : rclo;
            f4& ch = j < k ? lchi : rchi;
            l = lower(l, lo[p[j]]), h = upper(h, hi[p[j]]);
            cl = lower(cl, c[p[j]]), ch = upper(ch, c[p[j]]);
        }
        const int left = made, first = row[r].first;
        made += 2;
        row[r].first = left;  // an inner node: its box stays
        row[r].count = 0;
        const f4 box[4] = {llo, lhi, rlo, rhi};
        for (int q = 0; q < 2; ++q)
            for (int a = 0; a < 3; ++a) {
                row[left + q].lo.c[a] = box[2 * q][a];
                row[left + q].hi.c[a] = box[2 * q + 1][a];
            }
        row[left].first = first;
        row[left].count = k;
        row[left + 1].first = first + k;
        row[left + 1].count = count - k;
        st_row[sp] = left;
        st_axis[sp] = axis_of(lclo, lchi);
        st_row[sp + 1] = left + 1;
        st_axis[sp + 1] = axis_of(rclo, rchi);
        st_depth[sp] = st_depth[sp + 1] = d + 1;
        st_sorted[sp] = st_sorted[sp + 1] = axis;
        sp += 2;
    }
    for (int i = 0; i < total; ++i)
        it[i] = item[perm[i]];
    return wp::vec2i(made, deepest);
#else
    return wp::vec2i(0, 0);
#endif
""".replace("SMALL", str(int(SMALL_TASK)))


@wp.func_native(SUBTREE_SOURCE)
def subtree_rows_native(items: wp.array(dtype=BuildItem), nodes: wp.array(dtype=BvhNode),
                        rows: int, depth: int, max_depth: int, leaf_size: int,
                        whole_max: int) -> wp.vec2i:
    """subtree_rows (SUBTREE_SOURCE); (0, 0) where not compiled."""
    ...


@wp.func
def sort_small(b: BuildData, start: int, count: int, axis: int):
    """Sort a small range by centroid on `axis`: an insertion sort of (key, position) pairs
    held locally, then one pass through Swap's spare array (free here: the range is this
    worker's) to move the items."""
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
def small_subtree(b: BuildData, node: int, depth: int, worker: int):
    """Finish the subtree of a node written as a leaf. SAH: a range of at most SMALL_TASK
    triangles is built here, in the worker that made it, where the pool's phases would cost
    more than the work: each node is sorted on its longest centroid axis (unless its parent
    already sorted it so) and cut at the exact SAH minimum over all count - 1 planes, and
    becomes a leaf wherever that is cheaper (leaf_size is then a maximum, as in Embree).
    The nodes are made in the worker's own rows of `subtree_nodes`, row 0 the subtree's
    root (subtree_rows, natively on a CPU), and numbered at the end (number_subtree).
    Median: the node stays a leaf."""
    if b.method != METHOD_SAH:
        return
    rows = worker * SUBTREE_NODES
    b.subtree_nodes[rows] = b.nodes[node]
    made = subtree_rows_native(b.items, b.subtree_nodes, rows, depth, b.max_depth,
                               b.leaf_size, b.whole_max)
    if made[0] == 0:
        made = subtree_rows(b, rows, depth)
    shared_max(b.counters, MAX_DEPTH, made[1])
    number_subtree(b, node, rows, made[0])


@wp.func
def subtree_rows(b: BuildData, rows: int, depth: int) -> wp.vec2i:
    """small_subtree's nodes in the rows from `rows`: (rows made, deepest depth)."""
    n = b.subtree_nodes[rows]
    made = int(1)  # rows used: the root and the children made so far
    nodes = SmallInts()  # the stack: row, depth, split axis, axis the range is sorted by
    depths = SmallInts()
    axes = SmallInts()
    sorted_by = SmallInts()
    nodes[0] = 0
    depths[0] = depth
    axes[0] = centroid_axis(range_box(b, n.first, n.count)[2])
    sorted_by[0] = -1
    sp = int(1)
    deepest = depth
    while sp > 0:
        sp -= 1
        n = b.subtree_nodes[rows + nodes[sp]]
        d = depths[sp]
        axis = axes[sp]
        deepest = wp.max(deepest, d)
        if n.count <= b.whole_max or d >= b.max_depth - 1:
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
        left = made
        made += 2
        write_node(b.subtree_nodes, rows + nodes[sp], n.lo, n.hi, left, 0)
        lbox = range_box(b, n.first, k)
        rbox = range_box(b, n.first + k, n.count - k)
        write_node_box(b.subtree_nodes, rows + left, lbox, n.first, k)
        write_node_box(b.subtree_nodes, rows + left + 1, rbox, n.first + k, n.count - k)
        nodes[sp] = left
        axes[sp] = centroid_axis(lbox[2])
        nodes[sp + 1] = left + 1
        axes[sp + 1] = centroid_axis(rbox[2])
        for c in range(2):
            depths[sp + c] = d + 1
            sorted_by[sp + c] = axis
        sp += 2
    return wp.vec2i(made, deepest)


@wp.func
def number_subtree(b: BuildData, root: int, rows: int, made: int):
    """Copy a small subtree's `made` nodes from the worker's rows into `nodes`: row 0 to the
    root's number, the others to as many numbers taken from the shared counter at once (an
    inner node's child index moves with them). Numbered one by one, every split took the
    counter's cache line and wrote node lines that the other workers' nodes shared: two
    workers spent ~25% more time in the small subtrees than one."""
    if made == 1:
        return
    first = shared_add(b.counters, NODE_COUNT, made - 1) - 1  # row i > 0: node first + i
    for i in range(made):
        n = b.subtree_nodes[rows + i]
        if n.count == 0:
            n.first += first
        b.nodes[wp.where(i == 0, root, first + i)] = n
