"""Breadth-first parallel DACRT (Ravichandran & Narayanan 2013).

The implicit hierarchy is built and traversed one level at a time from the host:
  split     every node of the level at the midpoint of its largest extent
  filter    rays and triangles against the two halves: a status code per element, node
            number in the upper 30 bits, none/left/both/right (0..3) in the lower 2
            (sec. 2.1; 'none' is 0 here so that it fits the 2 bits)
  sort      `radix_sort_pairs` by status code (within each node, since nodes stay grouped)
  reduce    `runlength_encode` of the codes gives each node's four counts; child pivots
  children  with few triangles (< alpha) or rays (< beta) go to the terminal-node buffer,
            the rest to the next level (`array_scan` gives their offsets), gathered per element
  terminal  when the buffer passes its threshold: one thread per (node, ray) intersects the
            node's triangles (sec. 2.2), then a segmented minimum per ray: sort by ray id,
            `runlength_encode`, min over each run.
Rays and boxes use the same margins and classification as the task-pool variant
(`records.py`, `classify.py`), so the hits are those of `kernels.trace`.
"""

from __future__ import annotations

import time

import numpy as np
import warp as wp
from warp.utils import array_scan, radix_sort_pairs, runlength_encode

from ..core import mesh as core_mesh
from ..core.box import INF, median_plane
from ..core.compile_options import MODULE_OPTIONS
from ..core.device_arrays import DeviceArrays
from ..core.hits import Hits
from ..core.mesh import DeviceMesh
from ..core.ray import make_ray
from ..core.triangle import intersect_triangle
from . import records
from .classify import CLS_LEFT, CLS_RIGHT, ray_side, ray_span, side_of, widened_range
from .options import DacrtOptions
from .records import (
    KEY_NONE,
    TraceArrays,
    hit_key,
    rays_and_triangles,
    scene_box,
    unpack_hits,
)
from .stats import DacrtStats

wp.set_module_options(MODULE_OPTIONS)

NONE = wp.constant(0)
LEFT = wp.constant(1)
BOTH = wp.constant(2)
RIGHT = wp.constant(3)
KIND_NEXT = wp.constant(1)  # child goes to the next level
KIND_TERMINAL = wp.constant(2)  # child goes to the terminal-node buffer


@wp.struct
class Level:
    """The nodes of one level: boxes, split planes and pivots into the level's id lists."""

    lo: wp.array(dtype=wp.vec3)
    hi: wp.array(dtype=wp.vec3)
    axis: wp.array(dtype=int)
    split: wp.array(dtype=float)
    tri_start: wp.array(dtype=int)
    tri_count: wp.array(dtype=int)
    ray_start: wp.array(dtype=int)
    ray_count: wp.array(dtype=int)
    counts: wp.array(dtype=int)  # per node: triangles none/left/both/right, then rays


@wp.struct
class Children:
    """Two per node (left at 2k, right at 2k + 1)."""

    kind: wp.array(dtype=int)  # 0 none, KIND_NEXT, KIND_TERMINAL
    lo: wp.array(dtype=wp.vec3)
    hi: wp.array(dtype=wp.vec3)
    tri_first: wp.array(dtype=int)  # pivots into the sorted lists of this level
    tri_n: wp.array(dtype=int)
    ray_first: wp.array(dtype=int)
    ray_n: wp.array(dtype=int)
    next_tris: wp.array(dtype=int)  # tri_n for next-level children, else 0 (scanned: offset)
    next_rays: wp.array(dtype=int)
    next_nodes: wp.array(dtype=int)
    term_tris: wp.array(dtype=int)  # likewise for the terminal buffer
    term_rays: wp.array(dtype=int)
    term_nodes: wp.array(dtype=int)


@wp.kernel
def mark_node_starts(starts: wp.array(dtype=int), flags: wp.array(dtype=int)):
    k = wp.tid()
    if k > 0:
        flags[starts[k]] = 1


@wp.kernel
def split_level(lv: Level):
    """Midpoint of the largest extent (sec. 2)."""
    k = wp.tid()
    plane = median_plane(lv.lo[k], lv.hi[k])
    lv.axis[k] = int(plane[0])
    lv.split[k] = plane[1]


@wp.func
def code_of(side: int) -> int:
    if side == CLS_LEFT:
        return LEFT
    if side == CLS_RIGHT:
        return RIGHT
    return BOTH


@wp.kernel
def filter_tris(lv: Level, ids: wp.array(dtype=int), node_of: wp.array(dtype=int),
                tri_lo: wp.array(dtype=wp.vec3), tri_hi: wp.array(dtype=wp.vec3),
                keys: wp.array(dtype=wp.int32), values: wp.array(dtype=int)):
    """Status code of a triangle: none if its box misses the node's, else by the plane."""
    i = wp.tid()
    k = node_of[i]
    tri = ids[i]
    lo = tri_lo[tri]
    hi = tri_hi[tri]
    code = NONE
    nlo = lv.lo[k]
    nhi = lv.hi[k]
    if (lo[0] <= nhi[0] and lo[1] <= nhi[1] and lo[2] <= nhi[2] and hi[0] >= nlo[0]
            and hi[1] >= nlo[1] and hi[2] >= nlo[2]):
        a = lv.axis[k]
        code = code_of(side_of(wp.vec2(lo[a], hi[a]), lv.split[k], 0.0))
    keys[i] = wp.int32(k * 4 + code)
    values[i] = tri


@wp.kernel
def filter_rays(lv: Level, ids: wp.array(dtype=int), node_of: wp.array(dtype=int),
                d: TraceArrays, keys: wp.array(dtype=wp.int32), values: wp.array(dtype=int)):
    """Status code of a ray: none if it misses the node's box, else by its span's side."""
    i = wp.tid()
    k = node_of[i]
    ray = ids[i]
    r = d.rays[ray]
    w = widened_range(r)
    span = ray_span(r, lv.lo[k], lv.hi[k], w[0], w[1])
    code = NONE
    if span[0] < INF:
        code = code_of(ray_side(r, span, lv.axis[k], lv.split[k], d.margin))
    keys[i] = wp.int32(k * 4 + code)
    values[i] = ray


@wp.kernel
def count_runs(run_keys: wp.array(dtype=wp.int32), run_lengths: wp.array(dtype=int),
               offset: int, counts: wp.array(dtype=int)):
    """Reduce-by-key result -> counts[8 node + offset + code] (offset 0 tris, 4 rays)."""
    j = wp.tid()
    key = int(run_keys[j])
    counts[8 * (key / 4) + offset + key % 4] = run_lengths[j]


@wp.kernel
def make_children(lv: Level, ch: Children, depth: int, max_depth: int, alpha: int,
                  beta: int, margin: float):
    """Child pivots and boxes; terminal when few triangles or rays (sec. 2.1)."""
    k = wp.tid()
    tn = lv.counts[8 * k]
    tl = lv.counts[8 * k + 1]
    tb = lv.counts[8 * k + 2]
    tr = lv.counts[8 * k + 3]
    rn = lv.counts[8 * k + 4]
    rl = lv.counts[8 * k + 5]
    rb = lv.counts[8 * k + 6]
    rr = lv.counts[8 * k + 7]
    a = lv.axis[k]
    s = lv.split[k]
    for side in range(2):
        c = 2 * k + side
        lo = lv.lo[k]
        hi = lv.hi[k]
        tri_first = lv.tri_start[k] + tn
        ray_first = lv.ray_start[k] + rn
        tri_n = tl + tb
        ray_n = rl + rb
        if side == 0:
            hi[a] = wp.min(hi[a], s + margin)
        else:
            lo[a] = wp.max(lo[a], s - margin)
            tri_first += tl
            ray_first += rl
            tri_n = tb + tr
            ray_n = rb + rr
        kind = int(0)
        if tri_n > 0 and ray_n > 0:
            kind = KIND_NEXT
            if tri_n < alpha or ray_n < beta or depth + 1 >= max_depth:
                kind = KIND_TERMINAL
        ch.kind[c] = kind
        ch.lo[c] = lo
        ch.hi[c] = hi
        ch.tri_first[c] = tri_first
        ch.tri_n[c] = tri_n
        ch.ray_first[c] = ray_first
        ch.ray_n[c] = ray_n
        nxt = int(kind == KIND_NEXT)
        term = int(kind == KIND_TERMINAL)
        ch.next_tris[c] = nxt * tri_n
        ch.next_rays[c] = nxt * ray_n
        ch.next_nodes[c] = nxt
        ch.term_tris[c] = term * tri_n
        ch.term_rays[c] = term * ray_n
        ch.term_nodes[c] = term


@wp.kernel
def gather(sorted_ids: wp.array(dtype=int), node_of: wp.array(dtype=int), ch: Children,
           is_ray: int, next_ids: wp.array(dtype=int), term_ids: wp.array(dtype=int),
           term_base: int, term_node_base: int, term_seg: wp.array(dtype=int)):
    """Copy an element into each child it belongs to: the next level or the terminal buffer
    (a ray also records its terminal node there)."""
    i = wp.tid()
    k = node_of[i]
    for side in range(2):
        c = 2 * k + side
        first = ch.ray_first[c]
        n = ch.ray_n[c]
        if is_ray == 0:
            first = ch.tri_first[c]
            n = ch.tri_n[c]
        if i >= first and i < first + n:
            local = i - first
            if ch.kind[c] == KIND_NEXT:
                off = ch.next_rays[c]
                if is_ray == 0:
                    off = ch.next_tris[c]
                next_ids[off + local] = sorted_ids[i]
            elif ch.kind[c] == KIND_TERMINAL:
                off = ch.term_rays[c]
                if is_ray == 0:
                    off = ch.term_tris[c]
                term_ids[term_base + off + local] = sorted_ids[i]
                if is_ray != 0:
                    term_seg[term_base + off + local] = term_node_base + ch.term_nodes[c]


@wp.kernel
def next_level_nodes(ch: Children, lv: Level, term_tri_base: int, term_node_base: int,
                     seg_tri_start: wp.array(dtype=int), seg_tri_count: wp.array(dtype=int)):
    """Children to the next level become its nodes; terminal ones buffer segments."""
    c = wp.tid()
    if ch.kind[c] == KIND_NEXT:
        k = ch.next_nodes[c]
        lv.lo[k] = ch.lo[c]
        lv.hi[k] = ch.hi[c]
        lv.tri_start[k] = ch.next_tris[c]
        lv.tri_count[k] = ch.tri_n[c]
        lv.ray_start[k] = ch.next_rays[c]
        lv.ray_count[k] = ch.ray_n[c]
    elif ch.kind[c] == KIND_TERMINAL:
        s = term_node_base + ch.term_nodes[c]
        seg_tri_start[s] = term_tri_base + ch.term_tris[c]
        seg_tri_count[s] = ch.tri_n[c]


@wp.kernel
def intersect_segments(d: TraceArrays, ray_ids: wp.array(dtype=int),
                       ray_seg: wp.array(dtype=int), seg_tri_start: wp.array(dtype=int),
                       seg_tri_count: wp.array(dtype=int), tri_ids: wp.array(dtype=int),
                       keys: wp.array(dtype=wp.uint64)):
    """Segmented brute force (sec. 2.2, Algorithm 3): one thread per buffered ray."""
    j = wp.tid()
    ray = ray_ids[j]
    s = ray_seg[j]
    rec = d.rays[ray]
    r = make_ray(rec.origin, d.directions[ray])
    tmin = rec.tmin
    tmax = rec.tmax
    key = wp.uint64(KEY_NONE)
    first = seg_tri_start[s]
    for q in range(first, first + seg_tri_count[s]):
        tri = tri_ids[q]
        h = intersect_triangle(r, d.tri_verts[3 * tri], d.tri_verts[3 * tri + 1],
                               d.tri_verts[3 * tri + 2], tmin, tmax)
        if h[0] < INF:
            key = wp.min(key, hit_key(h[0], tri))
    keys[j] = key


@wp.kernel
def run_minimum(run_rays: wp.array(dtype=int), run_lengths: wp.array(dtype=int),
                run_starts: wp.array(dtype=int), keys: wp.array(dtype=wp.uint64),
                best: wp.array(dtype=wp.uint64)):
    """Segmented minimum per ray over the buffer, merged into the global closest hit."""
    j = wp.tid()
    m = best[run_rays[j]]
    first = run_starts[j]
    for q in range(first, first + run_lengths[j]):
        m = wp.min(m, keys[q])
    best[run_rays[j]] = m


class Terminal:
    """The terminal-node buffer: triangle and ray ids of buffered nodes (sec. 2.2)."""

    def __init__(self, mem, capacity: int):
        self.mem = mem
        self.capacity = capacity
        self.allocate(capacity)

    def allocate(self, capacity: int) -> None:
        new = self.mem.new
        self.capacity = capacity
        self.tri_ids = new(capacity, int)
        self.ray_ids = new(2 * capacity, int)  # room for radix_sort_pairs
        self.ray_seg = new(capacity, int)
        self.keys = new(2 * capacity, wp.uint64)
        self.seg_tri_start = new(capacity, int)
        self.seg_tri_count = new(capacity, int)
        self.tris = self.rays = self.nodes = 0

    def release(self) -> None:
        self.mem.free(self.tri_ids, self.ray_ids, self.ray_seg, self.keys, self.seg_tri_start,
                      self.seg_tri_count)

    def fits(self, tris: int, rays: int, nodes: int) -> bool:
        return (self.tris + tris <= self.capacity and self.rays + rays <= self.capacity
                and self.nodes + nodes <= self.capacity)

    def flush(self, d: TraceArrays, device) -> None:
        if self.rays == 0:
            self.tris = self.nodes = 0
            return
        n = self.rays
        wp.launch(intersect_segments, dim=n,
                  inputs=[d, self.ray_ids, self.ray_seg, self.seg_tri_start,
                          self.seg_tri_count, self.tri_ids, self.keys], device=device)
        radix_sort_pairs(self.ray_ids, self.keys, n)
        run_rays = self.mem.new(n, int)
        run_lengths = self.mem.new(n, int)
        runs = runlength_encode(self.ray_ids, run_rays, run_lengths, value_count=n)
        starts = self.mem.new(runs, int)
        array_scan(run_lengths[:runs], starts, inclusive=False)
        wp.launch(run_minimum, dim=runs,
                  inputs=[run_rays, run_lengths, starts, self.keys, d.best], device=device)
        self.mem.free(run_rays, run_lengths, starts)
        self.tris = self.rays = self.nodes = 0


def _scan_total(a: wp.array, out: wp.array) -> int:
    """Exclusive scan of a into out (in place is fine); returns the total."""
    last = int(a[-1:].numpy()[0])
    array_scan(a, out, inclusive=False)
    return int(out[-1:].numpy()[0]) + last


def breadth_first_trace(mesh: DeviceMesh, origins, directions, tmin, tmax, margin: float,
                        info: DacrtStats, opts: DacrtOptions) -> Hits:
    """The level loop of Algorithm 1 (sec. 2) on validated rays (`opts` resolved for the
    mesh's device); fills `info` with its statistics."""
    device = mesh.device
    ids = mesh.valid_ids()
    alpha, beta, max_depth = int(opts.alpha), int(opts.beta), int(opts.max_depth)
    buffer_entries = max(int(opts.buffer_entries), 1)
    t_start = time.perf_counter()
    mem = DeviceArrays(device)
    r, m, n = len(origins), len(mesh.indices), len(ids)
    d = rays_and_triangles(mem, mesh, origins, directions, tmin, tmax)
    d.margin = margin
    d.best = mem.new(max(r, 1), wp.uint64, fill=KEY_NONE)
    levels = 0
    peak_nodes = 0
    phase_s = dict.fromkeys(("filter", "sort", "reduce", "children", "gather", "intersect"), 0.0)
    if r and n:
        box_lo, box_hi = scene_box(mesh.vertices, mesh.indices, ids, margin)
        lv = _new_level(mem, 1, device)
        lv.lo.assign(wp.array([box_lo], dtype=wp.vec3, device=device))
        lv.hi.assign(wp.array([box_hi], dtype=wp.vec3, device=device))
        for a, v in ((lv.tri_start, 0), (lv.tri_count, n), (lv.ray_start, 0),
                     (lv.ray_count, r)):
            a.fill_(v)
        nodes, n_tris, n_rays = 1, n, r
        tri_list = mem.new(n, int, data=ids)
        ray_list = mem.new(r, int, data=np.arange(r, dtype=np.int32))
        term = Terminal(mem, min(buffer_entries, 2 * (n + r)))  # no bigger than needed
        depth = 0
        while nodes > 0:
            levels += 1
            peak_nodes = max(peak_nodes, nodes)
            t0 = time.perf_counter()
            wp.launch(split_level, dim=nodes, inputs=[lv], device=device)
            tri_node = _node_of(mem, lv.tri_start, nodes, n_tris, device)
            ray_node = _node_of(mem, lv.ray_start, nodes, n_rays, device)
            tri_keys = mem.new(2 * n_tris, wp.int32)
            tri_vals = mem.new(2 * n_tris, int)
            ray_keys = mem.new(2 * n_rays, wp.int32)
            ray_vals = mem.new(2 * n_rays, int)
            wp.launch(filter_tris, dim=n_tris,
                      inputs=[lv, tri_list, tri_node, d.tri_lo, d.tri_hi, tri_keys, tri_vals],
                      device=device)
            wp.launch(filter_rays, dim=n_rays,
                      inputs=[lv, ray_list, ray_node, d, ray_keys, ray_vals], device=device)
            mem.free(tri_list, ray_list)
            t1 = time.perf_counter()
            phase_s["filter"] += t1 - t0
            radix_sort_pairs(tri_keys, tri_vals, n_tris)
            radix_sort_pairs(ray_keys, ray_vals, n_rays)
            t2 = time.perf_counter()
            phase_s["sort"] += t2 - t1
            lv.counts.zero_()
            for keys, count, offset in ((tri_keys, n_tris, 0), (ray_keys, n_rays, 4)):
                run_keys = mem.new(count, wp.int32)
                run_lengths = mem.new(count, int)
                runs = runlength_encode(keys, run_keys, run_lengths, value_count=count)
                wp.launch(count_runs, dim=runs, inputs=[run_keys, run_lengths, offset,
                                                       lv.counts], device=device)
                mem.free(run_keys, run_lengths)
            mem.free(tri_keys, ray_keys)
            t3 = time.perf_counter()
            phase_s["reduce"] += t3 - t2
            ch = _new_children(mem, 2 * nodes, device)
            wp.launch(make_children, dim=nodes,
                      inputs=[lv, ch, depth, max_depth, alpha, beta, margin], device=device)
            next_tris = _scan_total(ch.next_tris, ch.next_tris)
            next_rays = _scan_total(ch.next_rays, ch.next_rays)
            next_nodes = _scan_total(ch.next_nodes, ch.next_nodes)
            t_tris = _scan_total(ch.term_tris, ch.term_tris)
            t_rays = _scan_total(ch.term_rays, ch.term_rays)
            t_nodes = _scan_total(ch.term_nodes, ch.term_nodes)
            t4 = time.perf_counter()
            phase_s["children"] += t4 - t3
            if not term.fits(t_tris, t_rays, t_nodes):
                term.flush(d, device)
                if not term.fits(t_tris, t_rays, t_nodes):
                    term.release()
                    term.allocate(2 * max(t_tris, t_rays, t_nodes))
            t5 = time.perf_counter()
            phase_s["intersect"] += t5 - t4
            new_lv = _new_level(mem, max(next_nodes, 1), device)
            wp.launch(next_level_nodes, dim=2 * nodes,
                      inputs=[ch, new_lv, term.tris, term.nodes, term.seg_tri_start,
                              term.seg_tri_count], device=device)
            new_tris = mem.new(max(next_tris, 1), int)
            new_rays = mem.new(max(next_rays, 1), int)
            wp.launch(gather, dim=n_tris,
                      inputs=[tri_vals, tri_node, ch, 0, new_tris, term.tri_ids, term.tris,
                              term.nodes, term.ray_seg], device=device)
            wp.launch(gather, dim=n_rays,
                      inputs=[ray_vals, ray_node, ch, 1, new_rays, term.ray_ids, term.rays,
                              term.nodes, term.ray_seg], device=device)
            term.tris += t_tris
            term.rays += t_rays
            term.nodes += t_nodes
            mem.free(tri_vals, ray_vals, tri_node, ray_node)
            _free_struct(mem, lv)
            _free_struct(mem, ch)
            lv, nodes, n_tris, n_rays = new_lv, next_nodes, next_tris, next_rays
            tri_list, ray_list = new_tris, new_rays
            depth += 1
            phase_s["gather"] += time.perf_counter() - t5
        t6 = time.perf_counter()
        term.flush(d, device)
        phase_s["intersect"] += time.perf_counter() - t6
    wp.synchronize_device(device)
    trace_ms = (time.perf_counter() - t_start) * 1e3
    hits = unpack_hits(mem, d, r)
    info.fill(variant="breadth_first", total_ms=(time.perf_counter() - t_start) * 1e3,
              trace_ms=trace_ms, phase_ms={k: s * 1e3 for k, s in phase_s.items()},
              peak_bytes=int(mem.peak), levels=levels, peak_nodes=peak_nodes,
              degenerate=int(m - n))
    return hits


def _node_of(mem, starts: wp.array, nodes: int, count: int, device) -> wp.array:
    """Node index of every element of a level list: marks at node starts, inclusive scan."""
    flags = mem.new(count, int, fill=0)
    wp.launch(mark_node_starts, dim=nodes, inputs=[starts, flags], device=device)
    array_scan(flags, flags, inclusive=True)
    return flags


def _new_level(mem, nodes: int, device) -> Level:
    lv = Level()
    for name in ("lo", "hi"):
        setattr(lv, name, mem.new(nodes, wp.vec3))
    lv.axis = mem.new(nodes, int)
    lv.split = mem.new(nodes, float)
    for name in ("tri_start", "tri_count", "ray_start", "ray_count"):
        setattr(lv, name, mem.new(nodes, int))
    lv.counts = mem.new(8 * nodes, int)
    return lv


def _new_children(mem, count: int, device) -> Children:
    ch = Children()
    ch.lo = mem.new(count, wp.vec3)
    ch.hi = mem.new(count, wp.vec3)
    for name in ("kind", "tri_first", "tri_n", "ray_first", "ray_n", "next_tris", "next_rays",
                 "next_nodes", "term_tris", "term_rays", "term_nodes"):
        setattr(ch, name, mem.new(count, int))
    return ch


def _free_struct(mem, s) -> None:
    mem.free(*(getattr(s, k) for k in s._cls.vars))


# the Warp modules a trace runs (loaded first: Warp's compile time is reported apart)
WARP_MODULES = (filter_rays.module, *records.WARP_MODULES, *core_mesh.WARP_MODULES)
