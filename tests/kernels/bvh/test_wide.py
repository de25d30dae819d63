"""The wide BVH: its structure, and its traversal against the float64 brute force
and against the binary tree, for every width, on deep trees, flat boxes and rays along
axes and in planes; the SIMD node test and traversal against the portable ones."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from scenesort.kernels.bvh import BvhArrays, wide
from scenesort.kernels.bvh import api as bvh_api
from scenesort.kernels.bvh.wide import WIDE_STACK, WideDists, WideStack
from scenesort.kernels.bvh.wide_traversal import (
    simd_lanes,
    simd_support,
    traverse_simd,
    traverse_wide_portable,
    wide_node_portable,
    wide_node_simd,
)
from scenesort.kernels.core.box import INF
from scenesort.kernels.core.ray import FAR_WIDEN, Hit, make_ray

from scenesort import kernels

from ..reference import (
    assert_same_hits,
    axis_aligned_cube_rays,
    brute_force,
    random_rays,
    random_soup,
)

WIDTHS = (2, 4, 8)


def decode(bvh) -> list[dict]:
    """The wide nodes as dicts of per-lane arrays (layout in kernels/bvh/wide.py)."""
    w = bvh.stats.width
    words = bvh.arrays.wide.numpy().reshape(-1, 8, w)
    ints = words.view(np.int32)
    return [{"lo": words[k, 0:6:2].T, "hi": words[k, 1:6:2].T, "child": ints[k, 6],
             "count": ints[k, 7]} for k in range(len(words))]


def same_as(a, b) -> None:
    """Bit-identical t, u, v and hit/miss; the triangle may differ only at equal t."""
    assert np.array_equal(a.triangle >= 0, b.triangle >= 0)
    assert np.array_equal(a.t, b.t)
    same = a.triangle == b.triangle
    assert np.array_equal(a.u[same], b.u[same]) and np.array_equal(a.v[same], b.v[same])


@pytest.mark.parametrize("width", [4, 8])
@pytest.mark.parametrize(("method", "leaf_size"), [("sah", 1), ("sah", 8), ("median", 16)])
def test_wide_tree_covers_every_triangle_once_with_tight_boxes(width, method, leaf_size):
    """Every leaf-order position in exactly one wide leaf, its blocks holding its triangles
    (the last block padded with its last one), every box tight around its triangles or its
    child's lanes, every wide node reached once, unused lanes empty."""
    rng = np.random.default_rng(3 + width)
    v, f = random_soup(rng, 700)
    bvh = kernels.build_bvh(v, f, method=method, leaf_size=leaf_size, width=width)
    assert bvh.stats.width == width
    nodes = decode(bvh)
    assert bvh.stats.wide_nodes == len(nodes)
    blocks = bvh.arrays.blocks.numpy().reshape(-1, 10, 4)
    corners = bvh.vertices[bvh.indices[bvh.permutation()]]  # (leaf position, vertex, xyz)
    covered = np.zeros(len(corners), dtype=int)
    reached = np.zeros(len(nodes), dtype=int)
    reached[0] = 1
    for k, n in enumerate(nodes):
        used = np.isfinite(n["lo"][:, 0])
        assert used.sum() >= (1 if k == 0 else 2), f"wide node {k} has {used.sum()} children"
        assert np.all(n["lo"][~used] == np.inf) and np.all(n["hi"][~used] == np.inf)
        assert np.all(n["count"][~used] == 0)
        for j in np.flatnonzero(used):
            if n["count"][j] > 0:
                block, count = int(n["child"][j]), int(n["count"][j])
                lanes = np.arange(count)
                rows = blocks[block + lanes // 4, :, lanes % 4]  # (count, 10)
                pos = rows[:, 9].copy().view(np.int32)
                assert np.array_equal(pos, pos[0] + lanes), f"lane {k}.{j}: leaf positions"
                tris = rows[:, :9].reshape(-1, 3, 3)
                assert np.array_equal(tris, corners[pos])
                if count % 4:
                    last = blocks[block + (count - 1) // 4]
                    assert np.all(last[:, count % 4:] == last[:, count % 4 - 1: count % 4])
                covered[pos] += 1
                assert np.array_equal(n["lo"][j], tris.min(axis=(0, 1)))
                assert np.array_equal(n["hi"][j], tris.max(axis=(0, 1)))
            else:
                c = int(n["child"][j])
                assert k < c < len(nodes), f"lane {k}.{j}: child {c}"
                reached[c] += 1
                kid = nodes[c]
                ok = np.isfinite(kid["lo"][:, 0])
                assert np.array_equal(n["lo"][j], kid["lo"][ok].min(axis=0))
                assert np.array_equal(n["hi"][j], kid["hi"][ok].max(axis=0))
    assert np.all(covered == 1), "a triangle is in no wide leaf or in several"
    assert np.all(reached == 1), "a wide node is reached from no parent or from several"
    assert bvh.stats.leaf_blocks == len(blocks)


def canonical(wide: np.ndarray, blocks: np.ndarray, width: int, k: int = 0) -> tuple:
    """Wide node k and everything below it, without the node and block numbers: per lane its
    box's bytes and its child's canonical form or its leaf's triangle positions."""
    words = wide.reshape(-1, 8, width)[k]
    ints = words.view(np.int32)
    out = []
    for j in range(width):
        child, count = int(ints[6, j]), int(ints[7, j])
        if count > 0:
            lanes = np.arange(count)
            below = tuple(blocks.reshape(-1, 10, 4)[child + lanes // 4, 9, lanes % 4]
                          .copy().view(np.int32))
        else:
            below = canonical(wide, blocks, width, child) if np.isfinite(words[0, j]) else ()
        out.append((words[:6, j].tobytes(), count, below))
    return tuple(out)


@pytest.mark.parametrize("width", [4, 8])
def test_collapse_is_the_same_tree_whatever_the_workers(width):
    """The workers collapse subtrees in whatever order they finish them, which only moves
    the subtrees' nodes and blocks within the arrays: the tree and its statistics are the
    same for 1 and 4 workers (4000 triangles: the top and a dozen subtrees of <= 512)."""
    v, f = random_soup(np.random.default_rng(8), 4000)
    bvh = kernels.build_bvh(v, f, width=2)
    nodes, n = bvh.arrays.nodes, len(bvh.permutation())
    trees = [wide.collapse(nodes, nodes.shape[0], bvh.arrays, n, width, bvh.device,
                           workers) for workers in (1, 4)]
    assert trees[0][2] == trees[1][2]
    assert trees[0][2]["wide_nodes"] > 20
    one, four = (canonical(a.numpy(), b.numpy(), width) for a, b, _ in trees)
    assert one == four


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize(("method", "leaf_size"), [("sah", 1), ("sah", 8), ("median", 4)])
def test_every_width_equals_brute_force(width, method, leaf_size):
    rng = np.random.default_rng(17 + width + leaf_size)
    v, f = random_soup(rng, 500)
    o, d = random_rays(rng, 800, -0.5, 1.5)
    tmin = rng.random(800).astype(np.float32) * 0.2
    tmax = tmin + 2.0 * rng.random(800).astype(np.float32)
    bvh = kernels.build_bvh(v, f, method=method, leaf_size=leaf_size, width=width)
    ref_t, ref_tri = brute_force(v, f, o, d, tmin, tmax)
    assert_same_hits(kernels.trace(bvh, o, d, tmin=tmin, tmax=tmax), ref_t, ref_tri)
    anyhit = kernels.trace(bvh, o, d, tmin=tmin, tmax=tmax, any_hit=True)
    assert np.array_equal(anyhit.triangle >= 0, ref_tri >= 0)
    got = anyhit.triangle >= 0
    assert np.all((anyhit.t[got] >= tmin[got]) & (anyhit.t[got] <= tmax[got]))


@pytest.mark.parametrize("width", [4, 8])
@pytest.mark.parametrize("name", ["sponza", "conference"])
def test_wide_equals_binary_on_shared_scenes(width, name, shared_scene):
    """Camera and random rays through a real scene: the same distances to the bit."""
    scene = shared_scene(name)
    v, f = scene.vertices, scene.indices
    cam = type(scene.camera).from_dict({**scene.camera.to_dict(), "width": 96, "height": 64})
    o1, d1, _, _ = cam.rays()
    rng = np.random.default_rng(8)
    lo, hi = v.min(axis=0), v.max(axis=0)
    o2 = (lo + (hi - lo) * rng.random((6000, 3))).astype(np.float32)
    d2 = rng.normal(size=(6000, 3)).astype(np.float32)
    o, d = np.vstack([o1, o2]), np.vstack([d1, d2])
    binary = kernels.build_bvh(v, f, width=2)
    wide = kernels.build_bvh(v, f, width=width)
    same_as(kernels.trace(wide, o, d), kernels.trace(binary, o, d))
    tmax = 0.1 * float(np.linalg.norm(hi - lo))
    occluded = [kernels.trace(b, o, d, tmax=tmax, any_hit=True).triangle >= 0
                for b in (wide, binary)]
    assert np.array_equal(*occluded)


def nested_triangles(levels: int) -> tuple[np.ndarray, np.ndarray]:
    """Triangles halving in size and distance towards the origin: the spatial median cuts
    one off per level, a chain as deep as `levels` (or the depth cap)."""
    tris = []
    for k in range(levels):
        s = np.float32(2.0) ** -k
        tris.append([[s, 0, 0], [s, s, 0], [s, 0, s]])
    v = np.asarray(tris, np.float32).reshape(-1, 3)
    return v, np.arange(len(v), dtype=np.int32).reshape(-1, 3)


@pytest.mark.parametrize("width", WIDTHS)
def test_deep_tree(width):
    """A chain that reaches the depth cap (63): every width finds the brute-force hits, and
    the wide tree's stack need stays within its stack."""
    v, f = nested_triangles(100)
    bvh = kernels.build_bvh(v, f, method="median", leaf_size=1, width=width)
    assert bvh.stats.depth == 63
    assert bvh.stats.width == width
    assert bvh.stats.wide_stack <= WIDE_STACK
    rng = np.random.default_rng(4)
    o = np.zeros((3000, 3), np.float32)
    o[:, 0] = -1.0
    d = np.column_stack([np.ones(3000), rng.random((3000, 2)) ** 4 * 0.5]).astype(np.float32)
    d[:, 0] = 1.0 + rng.random(3000)
    ref_t, ref_tri = brute_force(v, f, o, d)
    assert (ref_tri >= 0).sum() > 100
    assert_same_hits(kernels.trace(bvh, o, d), ref_t, ref_tri)
    assert np.array_equal(kernels.trace(bvh, o, d, any_hit=True).triangle >= 0, ref_tri >= 0)


def test_a_tree_needing_more_stack_is_traversed_as_binary(monkeypatch):
    monkeypatch.setattr(bvh_api, "WIDE_STACK", 2)
    v, f = random_soup(np.random.default_rng(5), 300)
    bvh = kernels.build_bvh(v, f, width=8)
    assert bvh.stats.width == 2 and bvh.arrays.width == 2
    o, d = random_rays(np.random.default_rng(6), 300, -0.5, 1.5)
    ref_t, ref_tri = brute_force(v, f, o, d)
    assert_same_hits(kernels.trace(bvh, o, d), ref_t, ref_tri)


@pytest.mark.parametrize("width", WIDTHS)
def test_flat_boxes_and_rays_in_their_plane(width):
    """A floor of triangles in the plane z = 0 (every floor box flat in z) and upright
    triangles through it; rays along the axes with -0.0 components, and rays lying in the
    plane z = 0 (origins on the flat boxes' faces, d_z = 0: the NaN path of the slab test):
    the same hits as the brute force and, bit for bit, as the binary tree."""
    v = []
    for qx in range(6):
        for qy in range(6):
            v += [[qx, qy, 0], [qx + 1, qy, 0], [qx, qy + 1, 0]]
            v += [[qx + 1, qy + 1, 0], [qx, qy + 1, 0], [qx + 1, qy, 0]]
            v += [[qx + 0.5, qy + 0.25, -0.5], [qx + 0.5, qy + 0.75, -0.5],
                  [qx + 0.5, qy + 0.5, 1.0]]
    v = np.asarray(v, np.float32)
    f = np.arange(len(v), dtype=np.int32).reshape(-1, 3)
    rng = np.random.default_rng(10)
    n = 2000
    o_down = np.column_stack([rng.random((n, 2)) * 6, np.full(n, 2.0)])
    d_down = np.tile([-0.0, -0.0, -1.0], (n, 1))
    o_plane = np.column_stack([rng.random(n) * 6, np.full(n, -1.0), np.zeros(n)])
    d_plane = np.column_stack([np.where(np.arange(n) % 2, rng.normal(size=n) * 0.2, 0.0),
                               np.ones(n), np.full(n, -0.0)])
    o_x = np.column_stack([np.full(n, -1.0), rng.random(n) * 6, rng.random(n) * 0.9])
    d_x = np.tile([1.0, 0.0, -0.0], (n, 1))
    o = np.vstack([o_down, o_plane, o_x]).astype(np.float32)
    d = np.vstack([d_down, d_plane, d_x]).astype(np.float32)
    bvh = kernels.build_bvh(v, f, leaf_size=2, width=width)
    hits = kernels.trace(bvh, o, d)
    assert (hits.triangle[:n] >= 0).all()
    assert (hits.triangle[n:2 * n] >= 0).sum() > n / 10  # the upright triangles
    assert (hits.triangle[2 * n:] >= 0).sum() > n / 10
    ref_t, ref_tri = brute_force(v, f, o, d)
    assert_same_hits(hits, ref_t, ref_tri)
    same_as(hits, kernels.trace(kernels.build_bvh(v, f, leaf_size=2, width=2), o, d))


@pytest.mark.parametrize("width", WIDTHS)
def test_axis_aligned_rays_and_empty_mesh(width):
    v, f, o, d = axis_aligned_cube_rays()
    h = kernels.trace(kernels.build_bvh(v, f, width=width), o, d)
    assert np.all(h.triangle >= 0) and np.all(h.t == 1.5)
    empty = kernels.build_bvh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32),
                              width=width)
    h = kernels.trace(empty, o, d)
    assert np.all(h.triangle == -1) and np.all(np.isinf(h.t))
    assert np.all(kernels.trace(empty, o, d, any_hit=True).triangle == -1)


def test_width_option(device):
    v, f = random_soup(np.random.default_rng(1), 50)
    bvh = kernels.build_bvh(v, f)
    assert bvh.stats.width == bvh_api.default_width(wp.get_device(device))
    assert bvh.stats.width == (8 if simd_support(device)[0] > 0 else 2)
    assert "collapse" in bvh.stats.phase_ms
    with pytest.raises(ValueError, match="width must be one of"):
        kernels.build_bvh(v, f, width=3)


@pytest.mark.host_only
def test_default_width_follows_the_simd_traversal_compiled_in(monkeypatch):
    """Width 8 where the SIMD traversal is compiled in (a CPU with AVX2), the binary tree
    where it is not: there the lane-by-lane wide traversal ran at 0.4-0.6x the binary one's
    speed (benchmarks/bvh.py --target-cpu x86-64, docs/architecture.md)."""
    v, f = random_soup(np.random.default_rng(1), 50)
    for support, width in (((0, 0), 2), ((8, 1), 8), ((8, 2), 8)):
        monkeypatch.setattr(bvh_api, "simd_support", lambda device, s=support: s)
        assert kernels.build_bvh(v, f).stats.width == width


def tricky_tree(width: int):
    """A tree with flat boxes (a third flat in each axis), its decoded nodes, and rays from
    box corners and faces, many aimed at a child box, with zero components (the NaN path)."""
    rng = np.random.default_rng(11)
    cells = rng.integers(0, 3, (200, 3)).astype(np.float32)
    tri = np.repeat(cells, 3, axis=0).reshape(200, 3, 3) + rng.random((200, 3, 3))
    for axis in range(3):  # a third of the triangles flat in each axis
        tri[axis::3, :, axis] = cells[axis::3, None, axis]
    tri = tri.astype(np.float32)
    f = np.arange(600, dtype=np.int32).reshape(-1, 3)
    bvh = kernels.build_bvh(tri.reshape(-1, 3), f, leaf_size=1, width=width)
    nodes = decode(bvh)
    corners = np.vstack([np.vstack([n["lo"], n["hi"]]) for n in nodes])
    corners = corners[np.isfinite(corners[:, 0])]
    count = 20000
    o = np.round(rng.random((count, 3)) * 3, 1).astype(np.float32)  # often on a face
    on_corner = rng.random(count) < 0.3
    o[on_corner] = corners[rng.integers(0, len(corners), on_corner.sum())]
    d = rng.normal(size=(count, 3)).astype(np.float32)
    aim = rng.random(count) < 0.6  # at the middle of one of its node's boxes
    for i in np.flatnonzero(aim):
        n = nodes[i % len(nodes)]
        lanes = np.flatnonzero(np.isfinite(n["lo"][:, 0]))
        j = lanes[rng.integers(0, len(lanes))]
        d[i] = 0.5 * (n["lo"][j] + n["hi"][j]) - o[i]
    d[rng.random((count, 3)) < 0.2] = 0.0
    d[np.all(d == 0, axis=1)] = [0.0, -0.0, 1.0]
    return bvh, nodes, o, d


@wp.kernel(enable_backward=False)
def node_tests(wide: wp.array(dtype=float), width: int, count: int, ordered: int,
               origins: wp.array(dtype=wp.vec3), directions: wp.array(dtype=wp.vec3),
               bvh: BvhArrays, out: wp.array(dtype=int, ndim=2)):
    """Visit wide node i % count with both node tests: the reference each returns, then
    what it left on the stack, from the top."""
    i = wp.tid()
    r = make_ray(origins[i], directions[i])
    node = 1 + i % count
    for k in range(2):
        stack = WideStack()
        dists = WideDists()
        sp = int(0)
        ref = int(0)
        if k == 0:
            ref = wide_node_simd(wide, width, node, r, 0.0, 1.0e30, ordered, FAR_WIDEN, stack,
                                 dists, sp)
        else:
            ref = wide_node_portable(bvh, node, r, 0.0, 1.0e30, ordered != 0, stack, dists,
                                     sp)
        out[i, 9 * k] = ref
        for j in range(8):
            out[i, 9 * k + 1 + j] = wp.where(j < sp, stack[wp.max(sp - 1 - j, 0)], 0)


@pytest.mark.host_only
@pytest.mark.parametrize("width", [4, 8])
def test_simd_node_test_equals_the_portable_one(width):
    """The AVX2 node test and the lane-by-lane one with intersect_box leave the same
    children in the same order (closest hit: near to far; any hit: lane order), on every
    node of a tree with flat boxes, for origins on box corners and faces and rays with zero
    components (the NaN path)."""
    if simd_lanes() == 0:
        pytest.skip("no AVX2 on this CPU")
    bvh, nodes, o, d = tricky_tree(width)
    count = len(o)
    for ordered in (1, 0):  # closest hit, any hit
        out = wp.zeros((count, 18), dtype=int)
        wp.launch(node_tests, dim=count,
                  inputs=[bvh.arrays.wide, width, len(nodes), ordered, wp.array(o, dtype=wp.vec3),
                          wp.array(d, dtype=wp.vec3), bvh.arrays, out])
        got = out.numpy()
        assert np.count_nonzero(got[:, 0]) > count / 4
        assert np.count_nonzero(got[:, 2]) > count / 50  # two or more hit children
        assert np.array_equal(got[:, :9], got[:, 9:])


@wp.kernel(enable_backward=False)
def both_traversals(bvh: BvhArrays, origins: wp.array(dtype=wp.vec3),
                    directions: wp.array(dtype=wp.vec3), tmax: wp.array(dtype=float),
                    any_hit: int, out_t: wp.array(dtype=float, ndim=2),
                    out_tri: wp.array(dtype=int, ndim=2)):
    """Ray i through traverse_simd (k = 0) and traverse_wide_portable (k = 1): t, u, v and
    leaf position before the refinement, and whether an any-hit ray stopped early."""
    i = wp.tid()
    r = make_ray(origins[i], directions[i])
    for k in range(2):
        hit = Hit()
        hit.t = INF
        hit.triangle = -1
        done = bool(False)
        if k == 0:
            done = traverse_simd(bvh.wide, bvh.blocks, bvh.width, r, 0.0, tmax[i],
                                 wp.where(any_hit != 0, 0, 1), FAR_WIDEN, hit) != 0
        else:
            done = traverse_wide_portable(bvh, r, 0.0, tmax[i], any_hit != 0, hit)
        out_t[i, 3 * k] = hit.t
        out_t[i, 3 * k + 1] = hit.u
        out_t[i, 3 * k + 2] = hit.v
        out_tri[i, 2 * k] = hit.triangle
        out_tri[i, 2 * k + 1] = wp.where(done, 1, 0)


@pytest.mark.host_only
@pytest.mark.parametrize("width", [4, 8])
def test_simd_traversal_equals_the_portable_one(width):
    """The AVX2 traversal (node test, stack, leaf blocks) and the lane-by-lane one with
    intersect_box and intersect_triangle find the same hit, bit for bit, with the same leaf
    position (closest hit: the same visit order; any hit: the same first hit), on a tree
    with flat boxes, for origins on box corners and faces and rays with zero components
    (the NaN path)."""
    if simd_lanes() == 0:
        pytest.skip("no AVX2 on this CPU")
    bvh, _, o, d = tricky_tree(width)
    count = len(o)
    rng = np.random.default_rng(12)
    tmax = np.where(rng.random(count) < 0.5, 1.0e30, rng.random(count) * 2).astype(np.float32)
    for any_hit in (0, 1):
        out_t = wp.zeros((count, 6), dtype=float)
        out_tri = wp.zeros((count, 4), dtype=int)
        wp.launch(both_traversals, dim=count,
                  inputs=[bvh.arrays, wp.array(o, dtype=wp.vec3), wp.array(d, dtype=wp.vec3),
                          wp.array(tmax, dtype=float), any_hit, out_t, out_tri])
        t, tri = out_t.numpy(), out_tri.numpy()
        assert np.count_nonzero(tri[:, 0] >= 0) > count / 4
        assert np.count_nonzero(tri[:, 0] < 0) > count / 20
        assert np.count_nonzero(tri[:, 1]) == (np.count_nonzero(tri[:, 0] >= 0) if any_hit
                                               else 0)
        assert np.array_equal(t[:, :3], t[:, 3:], equal_nan=True)
        assert np.array_equal(tri[:, :2], tri[:, 2:])
