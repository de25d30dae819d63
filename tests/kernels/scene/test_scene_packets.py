"""Closest-hit rays through a two-level scene in packets (kernels/scene/packet.py): the hits of
`traverse_scene` ray by ray, bit for bit, with instances that overlap, mirror, scale and
coincide (equal t: the lower instance wins whatever the order of the visits), per-ray
ranges, partial packets, and more instances than a packet holds (ray by ray). Occlusion
rays in groups: blocked exactly where `traverse_scene` finds a hit."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from scenesort.backend.render.scenes import framing_camera
from scenesort.kernels.bvh.packet import PACKET
from scenesort.kernels.bvh.wide_traversal import simd_support
from scenesort.kernels.scene.packet import (
    MAX_CANDIDATES,
    InstancePackets,
    instance_packets,
    packet_candidates,
    packet_top_ray,
    trace_scene_group,
)
from scenesort.kernels.scene.top import SceneArrays, enter_padded_box, top_ray

from scenesort import kernels

from .test_scene import instance_set, rotation, transform

pytestmark = pytest.mark.skipif(simd_support("cpu")[0] != 8,
                                reason="the packet traversal is compiled for AVX2 CPUs only")


@wp.kernel
def candidates_kernel(s: SceneArrays, origins: wp.array(dtype=wp.vec3),
                      directions: wp.array(dtype=wp.vec3), tmin: wp.array(dtype=float),
                      tmax: wp.array(dtype=float), scratch: InstancePackets,
                      count: wp.array(dtype=int)):
    p = wp.tid()
    first = p * PACKET
    count[p] = packet_candidates(s, origins, directions, tmin, tmax, first,
                                 wp.min(first + PACKET, origins.shape[0]), scratch)


def candidates(scene, o, d) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per packet of PACKET consecutive rays: how many instances it visits (-1: ray by
    ray), and the instances and entries from each packet's first ray."""
    n = len(o)
    scratch = instance_packets(n, "cpu")
    count = wp.empty(-(-n // PACKET), dtype=int)
    lo, hi = (wp.array(np.float32([x]), dtype=float) for x in (0.0, np.inf))
    wp.launch(candidates_kernel, dim=count.shape[0],
              inputs=[scene.arrays, wp.array(o, dtype=wp.vec3), wp.array(d, dtype=wp.vec3), lo,
                      hi, scratch, count])
    return count.numpy(), scratch.candidates.numpy(), scratch.entry.numpy()


def pixel_rays(camera, rng, pixels: int, scene=None, per_pixel: int = PACKET):
    """`per_pixel` rays through each of `pixels` random pixels (of those whose centre sees
    `scene`, if given), spread over about a pixel (a filtered film's camera rays),
    consecutive."""
    o, d, _, _ = camera.rays()
    seen = (np.arange(len(o)) if scene is None else
            np.flatnonzero(kernels.trace(scene, o, d, packets=False).instance >= 0))
    pick = rng.choice(seen, pixels, replace=False)
    po = np.repeat(o[pick], per_pixel, axis=0)
    spread = np.linalg.norm(d[1] - d[0])
    pd = np.repeat(d[pick], per_pixel, axis=0) + rng.uniform(-spread, spread, (len(po), 3))
    return po, pd.astype(np.float32)


def identical(a, b) -> None:
    for field in ("t", "triangle", "u", "v", "instance"):
        assert np.array_equal(getattr(a, field), getattr(b, field)), field


def scene_of(v, f, transforms):
    return kernels.build_scene([kernels.build_bvh(v, f)], np.zeros(len(transforms), np.int32),
                               np.asarray(transforms, np.float32))


def test_scene_packets_equal_single_rays(shared_scene):
    """The bunny under the test suite's instance set (identity, rotated, scaled, mirrored,
    far) and twice more at the identity's place (equal t everywhere on it: the lowest of
    the three wins), camera rays 64 a pixel with cutting per-ray ranges and a partial last
    packet."""
    sc = shared_scene("bunny")
    v, f = sc.vertices, sc.indices
    v = (v - v.mean(axis=0)) / np.abs(v - v.mean(axis=0)).max()
    rng = np.random.default_rng(3)
    transforms = np.concatenate([instance_set(rng)[:5], np.eye(3, 4, dtype=np.float32)[None],
                                 transform(rotation(rng), (0.8, 0.8, 0.8), (1, 1, -1))[None],
                                 np.eye(3, 4, dtype=np.float32)[None]])
    scene = scene_of(v, f, transforms)
    corners = np.array([[-4.5, -4.5, -2.5], [4.5, 4.5, 4.5]], np.float32)
    o, d = pixel_rays(framing_camera(corners, 160, 120), rng, 300, scene)
    o, d = o[:-17], d[:-17]  # a partial last packet
    tmin = rng.uniform(0.0, 0.5, len(o)).astype(np.float32)
    tmax = np.where(rng.random(len(o)) < 0.3, rng.uniform(5.0, 12.0, len(o)),
                    np.inf).astype(np.float32)
    count, _, _ = candidates(scene, o, d)
    assert (count >= 1).all() and (count >= 3).mean() > 0.1  # 0, 5 and 7 coincide
    for kw in ({}, {"tmin": tmin, "tmax": tmax}):
        packets = kernels.trace(scene, o, d, **kw)
        single = kernels.trace(scene, o, d, packets=False, **kw)
        identical(packets, single)
        hit = packets.instance >= 0
        assert hit.mean() > 0.5
        # coincident instances 0, 5 and 7: instance 0 is reported, never 5 or 7
        assert (packets.instance == 0).any() and not np.isin(packets.instance, (5, 7)).any()


def test_candidates_nearest_first_and_too_many_go_ray_by_ray(shared_scene):
    """A row of small instances along the view: each packet's candidates are sorted by
    entry; with more than MAX_CANDIDATES of them in every packet's way the packet goes ray
    by ray, with the same hits."""
    sc = shared_scene("bunny")
    v, f = sc.vertices, sc.indices
    v = (v - v.mean(axis=0)) / np.abs(v - v.mean(axis=0)).max()
    n = MAX_CANDIDATES + 8
    transforms = [transform(np.eye(3), (0.5, 0.5, 0.5), (0.0, 0.0, -3.0 * k))
                  for k in range(n)]
    scene = scene_of(v, f, transforms)
    rng = np.random.default_rng(4)
    o = np.tile(np.float32([0.0, 0.0, 5.0]), (8 * PACKET, 1))
    d = np.tile(np.float32([0.0, 0.0, -1.0]), (8 * PACKET, 1))
    d[:, :2] += rng.uniform(-2e-3, 2e-3, (len(d), 2)).astype(np.float32)
    count, _, _ = candidates(scene, o, d)
    assert (count == -1).all()
    identical(kernels.trace(scene, o, d), kernels.trace(scene, o, d, packets=False))

    few = scene_of(v, f, transforms[:6])
    count, cand, entry = candidates(few, o, d)
    assert (count == 6).all()
    for p in range(len(count)):
        e = entry[p * PACKET: p * PACKET + 6]
        assert (np.diff(e) >= 0).all()
        assert list(cand[p * PACKET: p * PACKET + 6]) == list(range(6))  # nearest is 0
    identical(kernels.trace(few, o, d), kernels.trace(few, o, d, packets=False))


@wp.kernel(enable_backward=False)
def groups_kernel(s: SceneArrays, origins: wp.array(dtype=wp.vec3),
                  directions: wp.array(dtype=wp.vec3), tmin: wp.array(dtype=float),
                  tmax: wp.array(dtype=float), scratch: InstancePackets,
                  out: wp.array(dtype=int)):
    first = wp.tid() * PACKET
    trace_scene_group(s, origins, directions, tmin, tmax, first,
                      wp.min(first + PACKET, origins.shape[0]), scratch, out)


def blocked_in_groups(scene, o, d, tmin, tmax) -> np.ndarray:
    n = len(o)
    out = wp.empty(n, dtype=int)
    wp.launch(groups_kernel, dim=-(-n // PACKET),
              inputs=[scene.arrays, wp.array(o, dtype=wp.vec3), wp.array(d, dtype=wp.vec3),
                      wp.array(tmin, dtype=float), wp.array(tmax, dtype=float),
                      instance_packets(n, "cpu"), out])
    return out.numpy() >= 0


def test_scene_groups_block_exactly_as_single_rays(shared_scene):
    """Occlusion rays in groups of 64 (trace_scene_group, as the film and the AO rounds
    trace them): blocked exactly where `traverse_scene` ray by ray finds a hit, through the
    instance set (rotated, scaled, mirrored, coincident instances) and through more
    instances than a group holds (ray by ray): 64 cosine-spread rays from each of a
    pixel's hits, short and long ranges, in camera order and shuffled, a partial last
    group."""
    sc = shared_scene("bunny")
    v, f = sc.vertices, sc.indices
    v = (v - v.mean(axis=0)) / np.abs(v - v.mean(axis=0)).max()
    rng = np.random.default_rng(5)
    sets = {"instance set": np.concatenate([instance_set(rng)[:5],
                                            np.eye(3, 4, dtype=np.float32)[None]]),
            "many": np.stack([transform(rotation(rng), (0.4, 0.4, 0.4),
                                        rng.uniform(-1.5, 1.5, 3))
                              for _ in range(MAX_CANDIDATES + 8)])}
    corners = np.array([[-4.5, -4.5, -2.5], [4.5, 4.5, 4.5]], np.float32)
    for name, transforms in sets.items():
        scene = scene_of(v, f, transforms)
        o, d = pixel_rays(framing_camera(corners, 160, 120), rng, 60, scene, per_pixel=1)
        hits = kernels.trace(scene, o, d, packets=False)
        o, d, t = o[hits.hit], d[hits.hit], hits.t[hits.hit]
        point = o + t[:, None] * d
        origins = np.repeat(point - 1e-3 * d, PACKET, axis=0).astype(np.float32)
        w = rng.normal(size=(len(origins), 3))
        w /= np.linalg.norm(w, axis=1, keepdims=True)
        w = np.where((w * np.repeat(d, PACKET, axis=0)).sum(1, keepdims=True) > 0, -w, w)
        w = w.astype(np.float32)
        tmax = rng.choice(np.float32([0.05, 0.3, 2.0, np.inf]), len(w))
        tmin = np.zeros(len(w), np.float32)
        for order in (np.arange(len(w) - 23), rng.permutation(len(w) - 23)):
            oo, ww, t0, t1 = origins[order], w[order], tmin[order], tmax[order]
            single = kernels.trace(scene, oo, ww, t0, t1, any_hit=True).instance >= 0
            assert 0.1 < single.mean() < 0.9, name
            assert np.array_equal(blocked_in_groups(scene, oo, ww, t0, t1), single), name
        count, _, _ = candidates(scene, origins, w)
        assert (count == -1).any() == (name == "many"), name


@wp.kernel
def entries_kernel(s: SceneArrays, origins: wp.array(dtype=wp.vec3),
                   directions: wp.array(dtype=wp.vec3), lo: wp.array(dtype=wp.vec3),
                   hi: wp.array(dtype=wp.vec3), tmax: float, rays: wp.array2d(dtype=float),
                   packet: wp.array(dtype=float)):
    b = wp.tid()  # one box, one packet of 8 rays
    first = b * 8
    for k in range(8):
        rays[b, k] = enter_padded_box(top_ray(s, origins[first + k], directions[first + k]),
                                      lo[b], hi[b], 0.0, tmax)
    packet[b] = enter_padded_box(packet_top_ray(s, origins, directions, first, first + 8),
                                 lo[b], hi[b], 0.0, tmax)


def test_packet_box_test_passes_wherever_a_ray_does():
    """The packet as one ray (packet_top_ray) enters every padded box that one of its rays
    enters, no later than that ray, and misses most boxes none enters: random packets of 8
    rays (spread origins, directions of any signs), random boxes, the walls of a steep
    slope."""
    rng = np.random.default_rng(7)
    boxes = 20000
    centre = rng.uniform(-3, 3, (boxes, 1, 3))
    o = (centre + rng.normal(0, rng.choice([1e-3, 0.1, 1.0], (boxes, 1, 1)), (boxes, 8, 3)))
    lo = rng.uniform(-4, 4, (boxes, 3))
    hi = lo + rng.uniform(0, 2, (boxes, 3)) ** 3
    # half the packets aimed at their box's centre, half anywhere
    aim = np.where(rng.random((boxes, 1, 1)) < 0.5, (0.5 * (lo + hi))[:, None] - centre,
                   rng.normal(size=(boxes, 1, 3)))
    d = aim + rng.normal(0, rng.choice([0.01, 0.3, 2.0], (boxes, 1, 1)), (boxes, 8, 3))
    scene = kernels.build_scene([kernels.build_bvh(np.eye(3, dtype=np.float32),
                                                   np.array([[0, 1, 2]], np.int32))],
                                np.zeros(1, np.int32), np.eye(3, 4, dtype=np.float32)[None])
    arrays = scene.arrays
    arrays.slope = 1e-3  # walls far steeper than any transform's bound
    rays = wp.empty((boxes, 8), dtype=float)
    packet = wp.empty(boxes, dtype=float)
    wp.launch(entries_kernel, dim=boxes,
              inputs=[arrays, wp.array(o.reshape(-1, 3).astype(np.float32), dtype=wp.vec3),
                      wp.array(d.reshape(-1, 3).astype(np.float32), dtype=wp.vec3),
                      wp.array(lo.astype(np.float32), dtype=wp.vec3),
                      wp.array(hi.astype(np.float32), dtype=wp.vec3), 10.0, rays, packet])
    rays, packet = rays.numpy(), packet.numpy()
    entered = np.isfinite(rays).any(axis=1)
    assert 0.1 < entered.mean() < 0.9
    assert np.isfinite(packet[entered]).all()
    assert (packet[entered] <= rays[entered].min(axis=1)).all()
    assert (~np.isfinite(packet[~entered])).mean() > 0.3  # a test that rejects

