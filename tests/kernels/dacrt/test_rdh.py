"""RDH (2012 paper, sec. 5.2): the samples' per-plane counts and child boxes, and where the
samples fall in a task's intervals."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from scenesort.kernels.core import DeviceArrays, DeviceMesh
from scenesort.kernels.core.box import INF
from scenesort.kernels.dacrt import classify, rdh
from scenesort.kernels.dacrt import task as dk
from scenesort.kernels.dacrt.records import margin_for, rays_and_triangles

from ..reference import random_rays, random_soup


@wp.kernel
def _rdh_both_ways(d: dk.DacrtData, t: dk.DacrtTask):
    """Pool slot 0: SplitPlane's two steps as the pool runs them (a sample stored once per
    axis and side, the suffixes and prefixes summed at the step's end). Slot 1: every sampled
    triangle and ray against every candidate plane, one at a time."""
    ns = rdh.sample_counts(t)
    task = t
    task.step = 0
    for c in range((ns[0] + 31) / 32):
        rdh.split_plane_chunk(d, task, 0, c)
    rdh.rdh_children(d, task, 0, 0)
    task.step = 1
    for c in range((ns[1] + 31) / 32):
        rdh.split_plane_chunk(d, task, 0, c)
    rdh.rdh_children(d, task, 0, 2)
    ints = dk.CAND_INTS
    boxes = dk.CAND_BOXES
    for s in range(ns[0]):
        tri = d.tri_ids[rdh.sample_position(t, 0, s)]
        lo = d.io.tri_lo[tri]
        hi = d.io.tri_hi[tri]
        for c in range(dk.PLANES):
            p = rdh.candidate(t, c)
            a = int(p[0])
            side = classify.side_of(wp.vec2(lo[a], hi[a]), p[1], 0.0)
            for right in range(2):
                if side != classify.CLS_RIGHT - 2 * right:  # left child: not right; right: not left
                    d.cand[ints + 4 * c + right] += 1
                    k = boxes + 2 * c + right
                    d.cand_lo[k] = wp.min(d.cand_lo[k], lo)
                    d.cand_hi[k] = wp.max(d.cand_hi[k], hi)
    for c in range(dk.PLANES):
        p = rdh.candidate(t, c)
        for right in range(2):
            k = boxes + 2 * c + right
            box = rdh.half_box(t, d.cand_lo[k], d.cand_hi[k], int(p[0]), p[1], right)
            if box[0][0] <= box[1][0] and box[0][1] <= box[1][1] and box[0][2] <= box[1][2]:
                box = classify.widen(box[0], box[1], d.io.margin)
            d.cand_lo[k] = box[0]
            d.cand_hi[k] = box[1]
    for s in range(ns[1]):
        ray = d.ray_ids[rdh.sample_position(t, 1, s)]
        r = d.io.rays[ray]
        w = classify.widened_range(r)
        if classify.ray_span(r, t.lo, t.hi, w[0], w[1])[0] < INF:
            for c in range(dk.PLANES):
                for right in range(2):
                    if rdh.hits_child(d, r, w, boxes + 2 * c + right):
                        d.cand[ints + 4 * c + 2 + right] += 1


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("snap", [False, True])
def test_rdh_samples_equal_the_plane_by_plane_count(seed, snap, device):
    """The binary searches over the monotone child boxes count every sampled triangle and
    ray in exactly the children that testing each candidate plane in turn does, with the
    same child boxes; `snap` puts half the vertex coordinates exactly on candidate planes
    (node box [0, 1]^3: 10, 10 and 12 planes at (i + 0.5) / n)."""
    rng = np.random.default_rng(seed)
    v, f = random_soup(rng, 900)
    if snap:
        for a, n in enumerate((10, 10, 12)):
            planes = (np.arange(n, dtype=np.float32) + np.float32(0.5)) / np.float32(n)
            near = planes[np.abs(v[:, a, None] - planes).argmin(axis=1)]
            v[:, a] = np.where(rng.random(len(v)) < 0.5, near, v[:, a])
    o, d = random_rays(rng, 4000, -0.2, 1.2)
    r, n = len(o), len(f)
    mem = DeviceArrays(wp.get_device(device))
    io = rays_and_triangles(mem, DeviceMesh(v, f, device), o, d, np.zeros(r, np.float32),
                            np.full(r, np.inf, np.float32))
    io.margin = margin_for(v, o)
    data = dk.DacrtData()
    data.io = io
    data.ray_ids = wp.array(np.arange(r, dtype=np.int32), dtype=int)
    data.tri_ids = wp.array(np.arange(n, dtype=np.int32), dtype=int)
    data.cand = wp.zeros(2 * dk.CAND_INTS, dtype=wp.int32)
    data.cand_lo = wp.full(2 * dk.CAND_BOXES, wp.vec3(np.inf), dtype=wp.vec3)
    data.cand_hi = wp.full(2 * dk.CAND_BOXES, wp.vec3(-np.inf), dtype=wp.vec3)
    task = dk.DacrtTask()
    task.ray_count, task.tri_count = r, n
    task.lo = wp.vec3(0.0, 0.0, 0.0)  # the soup lies in the unit cube
    task.hi = wp.vec3(1.0, 1.0, 1.0)
    wp.launch(_rdh_both_ways, dim=1, inputs=[data, task], device=device)
    counts = data.cand.numpy().reshape(2, dk.PLANES, 4)
    assert np.array_equal(counts[0], counts[1])
    assert counts[1, :, 2:].sum() > 0 and counts[1, :, :2].min() >= 0  # rays were counted
    for a in (data.cand_lo, data.cand_hi):
        boxes = a.numpy().reshape(2, dk.PLANES, 2, 3)
        assert np.array_equal(boxes[0], boxes[1])


@wp.kernel
def _sample_positions(t: dk.DacrtTask, step: int, out: wp.array(dtype=int)):
    s = wp.tid()
    out[s] = rdh.sample_position(t, step, s)


@pytest.mark.parametrize("width", [512, 1024])
def test_rdh_ray_samples_do_not_alias_with_image_rows(width, device):
    """The root of a width² image holds its rays in row order and samples sqrt(width²) =
    width of them: with a fixed stride of width rays every sample was a pixel of column 0.
    One sample per stratum, at a hashed place: the samples spread over the columns and stay
    one per stratum."""
    task = dk.DacrtTask()
    task.ray_start, task.ray_count = 0, width * width
    task.tri_start, task.tri_count = 0, 100_000
    for step, count in ((1, width * width), (0, 100_000)):
        n = int(np.sqrt(count))
        out = wp.empty(n, dtype=int)
        wp.launch(_sample_positions, dim=n, inputs=[task, step, out], device=device)
        pos = out.numpy()
        stride = count // n
        assert np.array_equal(pos // stride, np.arange(n))  # one in each stratum, in range
        if step == 1:
            assert len(np.unique(pos % width)) > width // 2  # columns: ~63% of them by chance
