"""Rays traced together (kernels/bvh/packet.py): closest-hit rays in packets (wide_packet.h)
and any-hit rays in groups (wide_occlusion.h) give the same hits, bit for bit, as the
single-ray traversal, and the float64 brute force's; which packets and groups the native
traversals take and which they decline; equal-t ties resolved alike by every traversal."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from scenesort.backend.tools.peers import ao_rays
from scenesort.kernels.bvh import BvhArrays
from scenesort.kernels.bvh.packet import (
    GROUP,
    PACKET,
    packets_apply,
    traverse_occlusion_simd,
    traverse_packet_simd,
)
from scenesort.kernels.bvh.wide_traversal import simd_support
from scenesort.kernels.core.ray import FAR_WIDEN

from scenesort import kernels

from ..reference import assert_same_hits, brute_force, random_soup

pytestmark = pytest.mark.skipif(simd_support("cpu")[0] != 8,
                                reason="the packet traversal is compiled for AVX2 CPUs only")


@wp.kernel
def packets_taken(bvh: BvhArrays, origins: wp.array(dtype=wp.vec3),
                  directions: wp.array(dtype=wp.vec3), tmin: wp.array(dtype=float),
                  tmax: wp.array(dtype=float), out_t: wp.array(dtype=float),
                  out_triangle: wp.array(dtype=int), out_u: wp.array(dtype=float),
                  out_v: wp.array(dtype=float), any_hit: int, taken: wp.array(dtype=int)):
    p = wp.tid()
    if any_hit == 0:
        first = p * PACKET
        taken[p] = traverse_packet_simd(bvh.wide, bvh.blocks, bvh.width, origins, directions,
                                        tmin, tmax, first,
                                        wp.min(first + PACKET, origins.shape[0]), FAR_WIDEN,
                                        bvh.tri_ids, 0, out_t, out_triangle, out_u, out_v)
    else:
        first = p * GROUP
        taken[p] = traverse_occlusion_simd(bvh.wide, bvh.blocks, bvh.width, origins,
                                           directions, tmin, tmax, first,
                                           wp.min(first + GROUP, origins.shape[0]), FAR_WIDEN,
                                           out_t, out_triangle, out_u, out_v)


def taken(bvh, o, d, tmin=0.0, tmax=np.inf, any_hit=False) -> np.ndarray:
    """Per packet of PACKET consecutive rays (any_hit: per group of GROUP): 1 where the
    native traversal took it."""
    n = len(o)
    size = GROUP if any_hit else PACKET
    arr = [wp.array(np.broadcast_to(np.float32(x), (n,)).copy(), dtype=float)
           for x in (tmin, tmax)]
    outs = [wp.empty(n, dtype=dt) for dt in (float, int, float, float)]
    flags = wp.zeros((n + size - 1) // size, dtype=int)
    wp.launch(packets_taken, dim=flags.shape[0],
              inputs=[bvh.arrays, wp.array(o, dtype=wp.vec3), wp.array(d, dtype=wp.vec3), *arr,
                      *outs, int(any_hit), flags])
    return flags.numpy()


def single(bvh, o, d, **kw):
    """kernels.trace ray by ray."""
    return kernels.trace(bvh, o, d, packets=False, **kw)


def identical(a, b) -> None:
    for name in ("t", "triangle", "u", "v"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name


def tiles(o, d, width, height, k=8):
    """Camera rays (row-major) reordered into k x k tiles."""
    idx = np.arange(width * height).reshape(height, width)
    idx = idx.reshape(height // k, k, width // k, k).transpose(0, 2, 1, 3).ravel()
    return o[idx], d[idx]


@pytest.mark.parametrize("name", ["sponza", "conference", "bunny"])
def test_camera_packets_equal_single_rays_on_shared_scenes(name, shared_scene):
    """Camera rays in rows and in 8x8 tiles, with a tmax that cuts some hits: t, u, v and the
    triangle bit for bit as ray by ray; most tiles taken (not those where a direction
    component changes sign)."""
    scene = shared_scene(name)
    bvh = kernels.build_bvh(scene.vertices, scene.indices)
    cam = type(scene.camera).from_dict({**scene.camera.to_dict(), "width": 160, "height": 120})
    o, d, _, _ = cam.rays()
    diag = float(np.linalg.norm(np.ptp(scene.vertices, axis=0)))
    for oo, dd in ((o, d), tiles(o, d, 160, 120)):
        for tmax in (np.inf, 0.4 * diag):
            identical(kernels.trace(bvh, oo, dd, tmax=tmax),
                      single(bvh, oo, dd, tmax=tmax))
    assert taken(bvh, *tiles(o, d, 160, 120)).mean() > 0.75


def test_finished_packets_clamp_to_each_rays_range(shared_scene):
    """A packet's hits are finished in native code (four float64 refinements a vector): with
    each ray's range ending or starting at its own float32 hit (the refined t clamped to the
    range on one side or the other, or the hit cut), t, u, v and the triangle bit for bit
    as ray by ray, where `leaf.finish_hit` refines them."""
    scene = shared_scene("sponza")
    bvh = kernels.build_bvh(scene.vertices, scene.indices)
    cam = type(scene.camera).from_dict({**scene.camera.to_dict(), "width": 96, "height": 96})
    o, d, _, _ = cam.rays()
    o, d = tiles(o, d, 96, 96)
    t = kernels.trace(bvh, o, d).t
    t = np.where(np.isfinite(t), t, np.float32(1e30)).astype(np.float32)
    below = np.nextafter(t, np.float32(0)).astype(np.float32)
    above = np.nextafter(t, np.float32(np.inf)).astype(np.float32)
    for kw in ({"tmax": t}, {"tmax": below}, {"tmin": t}, {"tmin": above}):
        hits = kernels.trace(bvh, o, d, **kw)
        assert (hits.triangle >= 0).sum() > len(o) / 10
        identical(hits, single(bvh, o, d, **kw))
    assert taken(bvh, o, d).mean() > 0.75


def test_packets_equal_brute_force_with_per_ray_ranges():
    """A pinhole's rays over a random soup, tmin and tmax per ray, 1000 rays (the last packet
    partial): the float64 brute force's hits, and bit for bit the single rays'."""
    rng = np.random.default_rng(5)
    v, f = random_soup(rng, 3000)
    bvh = kernels.build_bvh(v, f)
    n = 1000
    a = np.linspace(0.02, 0.3, n, dtype=np.float32)
    o = np.tile(np.float32([0.4, 0.4, -1.0]), (n, 1))
    d = np.column_stack([a, np.sin(7 * a) * 0.3, np.ones(n)]).astype(np.float32)
    tmin = (rng.random(n) * 1.2).astype(np.float32)
    tmax = tmin + rng.random(n).astype(np.float32)
    hits = kernels.trace(bvh, o, d, tmin=tmin, tmax=tmax)
    assert taken(bvh, o, d).all()
    ref_t, ref_tri = brute_force(v, f, o, d, tmin, tmax)
    assert (ref_tri >= 0).sum() > n / 4
    assert_same_hits(hits, ref_t, ref_tri)
    identical(hits, single(bvh, o, d, tmin=tmin, tmax=tmax))


def test_incoherent_packets_are_declined_and_traced_ray_by_ray():
    """Packets with a zero direction component, directions of two signs on an axis,
    directions over an octant or origins across the scene are declined; their rays get the
    single-ray hits all the same."""
    rng = np.random.default_rng(6)
    v, f = random_soup(rng, 2000)
    bvh = kernels.build_bvh(v, f)
    n = PACKET
    pin = np.tile(np.float32([0.5, 0.5, -1.0]), (n, 1))
    cone = np.column_stack([np.linspace(0.01, 0.2, n), np.full(n, 0.05), np.ones(n)])
    cases = {
        "zero component": (pin, np.where(np.arange(n)[:, None] == 7, [0.0, 0.05, 1.0], cone)),
        "two signs": (pin, np.column_stack([np.linspace(-0.1, 0.1, n), np.linspace(-0.1, 0.1, n),
                                            np.ones(n)])),
        "an octant": (pin, np.abs(rng.normal(size=(n, 3))) + 0.01),
        "scattered origins": (rng.random((n, 3)) * [1, 1, 0.1] - [0, 0, 1], cone),
        "coherent": (pin, cone),
    }
    for label, (o, d) in cases.items():
        o, d = o.astype(np.float32), d.astype(np.float32)
        assert taken(bvh, o, d)[0] == (label == "coherent"), label
        identical(kernels.trace(bvh, o, d), single(bvh, o, d))


def test_equal_t_ties_give_the_first_leaf_position_in_every_traversal(shared_scene):
    """Conference's 512x512 camera rays meet overlapping coplanar triangles, where hits tie
    at equal t and the traversals visit them in different orders (each found a different
    triangle, and so a different refined t, before ties went to the first leaf position):
    the binary tree, the wide trees ray by ray and the packets report the same hits."""
    scene = shared_scene("conference")
    v, f = scene.vertices, scene.indices
    cam = type(scene.camera).from_dict({**scene.camera.to_dict(), "width": 512, "height": 512})
    o, d, _, _ = cam.rays()
    bvh = kernels.build_bvh(v, f)
    assert packets_apply(bvh)
    packets = kernels.trace(bvh, o, d)
    identical(packets, single(bvh, o, d))
    for width in (2, 4):
        identical(packets, kernels.trace(kernels.build_bvh(v, f, width=width), o, d))


@pytest.mark.parametrize("name", ["sponza", "conference", "dragon"])
def test_any_hit_groups_equal_single_rays_on_shared_scenes(name, shared_scene):
    """AO rays (4 cosine rays a camera hit, tmax 0.1 x diagonal), in camera order and
    shuffled: every group taken, and each ray's first hit (triangle, t, u, v) bit for bit
    the one its own any-hit traversal finds, which depends on the order of the visits."""
    scene = shared_scene(name)
    v, f = scene.vertices, scene.indices
    bvh = kernels.build_bvh(v, f)
    cam = type(scene.camera).from_dict({**scene.camera.to_dict(), "width": 96, "height": 72})
    o, d, _, _ = cam.rays()
    hits = kernels.trace(bvh, o, d)
    ao_o, ao_d = ao_rays(v, f, o, d, hits.t, hits.triangle, per_hit=4)
    tmax = 0.1 * float(np.linalg.norm(np.ptp(v, axis=0)))
    shuffled = np.random.default_rng(3).permutation(len(ao_o))
    for oo, dd in ((ao_o, ao_d), (ao_o[shuffled], ao_d[shuffled])):
        assert taken(bvh, oo, dd, tmax=tmax, any_hit=True).all()
        grouped = kernels.trace(bvh, oo, dd, tmax=tmax, any_hit=True)
        assert 0.1 < (grouped.triangle >= 0).mean() < 0.9
        identical(grouped, single(bvh, oo, dd, tmax=tmax, any_hit=True))


def test_any_hit_groups_equal_brute_force_with_per_ray_ranges():
    """Rays from a few points over a random soup, tmin and tmax per ray, 1000 rays (the last
    group partial): occluded exactly where the float64 brute force finds a hit, and bit for
    bit the single rays' first hits."""
    rng = np.random.default_rng(8)
    v, f = random_soup(rng, 3000)
    bvh = kernels.build_bvh(v, f)
    n = 1000
    o = np.repeat(rng.random((n // 8, 3)).astype(np.float32), 8, axis=0)
    d = rng.normal(size=(n, 3)).astype(np.float32)
    tmin = (rng.random(n) * 0.05).astype(np.float32)
    tmax = tmin + (rng.random(n) * 0.3).astype(np.float32)
    assert taken(bvh, o, d, any_hit=True).all()
    hits = kernels.trace(bvh, o, d, tmin=tmin, tmax=tmax, any_hit=True)
    _, ref_tri = brute_force(v, f, o, d, tmin, tmax)
    assert 0.2 < (ref_tri >= 0).mean() < 0.8
    assert np.array_equal(hits.triangle >= 0, ref_tri >= 0)
    identical(hits, single(bvh, o, d, tmin=tmin, tmax=tmax, any_hit=True))


def test_any_hit_groups_with_a_zero_direction_component_are_declined():
    """A group holding a ray with a zero direction component (the single traversal's careful
    path) is declined and traced ray by ray: the same hits all the same."""
    rng = np.random.default_rng(9)
    v, f = random_soup(rng, 100)
    bvh = kernels.build_bvh(v, f)
    o = np.tile(np.float32([0.5, 0.5, 0.5]), (2 * GROUP, 1))
    d = rng.normal(size=(2 * GROUP, 3)).astype(np.float32)
    d[GROUP + 5] = [0.0, 0.3, 1.0]
    assert list(taken(bvh, o, d, any_hit=True)) == [1, 0]
    hits = kernels.trace(bvh, o, d, tmax=0.1, any_hit=True)
    assert 0 < (hits.triangle >= 0).sum() < 2 * GROUP
    identical(hits, single(bvh, o, d, tmax=0.1, any_hit=True))
