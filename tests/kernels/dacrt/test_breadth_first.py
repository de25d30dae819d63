"""Breadth-first parallel DACRT (2013 paper) specifics: status codes, the terminal-node
buffer, thresholds and peak memory. Equality with the BVH tracer on random meshes, shared
scenes and the hypothesis properties run in test_api.py for both variants."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from scenesort.kernels import DacrtStats, dacrt_trace
from scenesort.kernels.core import DeviceArrays
from scenesort.kernels.dacrt import breadth_first as bf

from scenesort import kernels

from ..reference import assert_same_hits, random_rays, random_soup


def test_triangle_status_codes(device):
    """Node number in the upper 30 bits, none/left/both/right = 0..3 in the lower 2."""
    mem = DeviceArrays(wp.get_device(device))
    lv = bf._new_level(mem, 2, device)
    lv.lo.assign(np.array([[0, 0, 0], [10, 0, 0]], np.float32))
    lv.hi.assign(np.array([[4, 1, 1], [14, 1, 1]], np.float32))
    wp.launch(bf.split_level, dim=2, inputs=[lv], device=device)
    assert list(lv.axis.numpy()) == [0, 0] and list(lv.split.numpy()) == [2.0, 12.0]
    tri_lo = np.array([[0.5, 0, 0], [2.5, 0, 0], [1.5, 0, 0], [2, 0, 0], [20, 0, 0]], np.float32)
    tri_hi = tri_lo + np.float32(0.5)
    # triangles 0-3 in node 0 (left, right, both, both: touching the plane), 4 in node 1
    # (outside its box: none)
    node_of = wp.array([0, 0, 0, 0, 1], dtype=int)
    keys = wp.empty(5, dtype=wp.int32)
    values = wp.empty(5, dtype=int)
    wp.launch(bf.filter_tris, dim=5,
              inputs=[lv, wp.array(np.arange(5), dtype=int), node_of,
                      wp.array(tri_lo, dtype=wp.vec3), wp.array(tri_hi, dtype=wp.vec3), keys,
                      values], device=device)
    k = keys.numpy()
    assert list(k >> 2) == [0, 0, 0, 0, 1]
    assert list(k & 3) == [bf.LEFT, bf.RIGHT, bf.BOTH, bf.BOTH, bf.NONE]


@pytest.mark.parametrize(("alpha", "buffer_entries"), [(4, 64), (8, 1 << 12), (10**6, 1 << 20)])
def test_thresholds_and_buffer_flushes_give_the_same_hits(alpha, buffer_entries):
    """Deep hierarchies with a tiny buffer (many flushes, a buffer that must grow), and a
    root that is terminal at once, all equal the BVH tracer."""
    rng = np.random.default_rng(alpha)
    v, f = random_soup(rng, 2500)
    o, d = random_rays(rng, 4000, -0.5, 1.5)
    ref = kernels.trace(kernels.build_bvh(v, f), o, d)
    stats = DacrtStats()
    h = dacrt_trace(v, f, o, d, variant="breadth_first", alpha=alpha, beta=alpha,
                    buffer_entries=buffer_entries, stats=stats)
    assert_same_hits(h, ref.t, ref.triangle)
    assert (stats.levels == 1) == (alpha >= 2500)
    assert set(stats.phase_ms) == {"filter", "sort", "reduce", "children", "gather",
                                      "intersect"}


def test_depth_cap_makes_every_child_terminal():
    rng = np.random.default_rng(4)
    v, f = random_soup(rng, 1500)
    o, d = random_rays(rng, 2000, -0.5, 1.5)
    ref = kernels.trace(kernels.build_bvh(v, f), o, d)
    stats = DacrtStats()
    h = dacrt_trace(v, f, o, d, variant="breadth_first", alpha=1, beta=1, max_depth=3,
                    stats=stats)
    assert stats.levels <= 3
    assert_same_hits(h, ref.t, ref.triangle)


def test_peak_memory_is_reported_and_counts_the_buffer():
    rng = np.random.default_rng(6)
    v, f = random_soup(rng, 3000)
    o, d = random_rays(rng, 6000, -0.5, 1.5)
    inputs = o.nbytes + d.nbytes + 2 * 4 * len(o) + 3 * v.nbytes
    for entries in (1 << 10, 1 << 14):
        stats = DacrtStats()
        dacrt_trace(v, f, o, d, variant="breadth_first", buffer_entries=entries, stats=stats)
        # the buffer's arrays: 2 * 4 (ray ids) + 4 (segments) + 2 * 8 (keys) + 3 * 4 per entry
        assert stats.peak_bytes >= inputs + 40 * entries
