"""Rays through a two-level scene together: closest-hit rays in packets (camera rays), the
instances that any ray of a packet may enter, nearest entry first, each traced as one packet
in its object space (bvh/packet.py), every ray's closest hit kept as the top level keeps it
(top.keep_instance_hit: which instance wins does not depend on the order of the visits), so
the hits are `traverse_scene`'s, bit for bit; and occlusion rays in groups the same way,
each instance traced as one group of the rays not yet blocked, so whether a ray is blocked
is `traverse_scene`'s answer (which triangle blocks it may differ: any hit is the first
found, and the order of the instances is the group's).
"""

from __future__ import annotations

import warp as wp

from ..bvh.binary_traversal import NodeStack
from ..bvh.packet import (
    PACKET,
    read_hit,
    trace_occlusion_group,
    trace_packet_leaf_order,
    write_hit,
)
from ..bvh.wide_traversal import simd_support
from ..core.box import INF
from ..core.claim import Claims, claimed_items
from ..core.compile_options import MODULE_OPTIONS
from ..core.device_arrays import struct_of_arrays
from ..core.ray import flag_invalid_rays, per_ray
from .top import (
    InstanceHit,
    SceneArrays,
    TopRay,
    enter_padded_box,
    finish_instance_hit,
    keep_instance_hit,
    mesh_view,
    no_instance_hit,
    object_coords,
    top_walls,
    traverse_scene,
)

wp.set_module_options(MODULE_OPTIONS)

MAX_CANDIDATES = 32  # instances one packet visits (at most one a ray); more: ray by ray


@wp.struct
class InstancePackets:
    """Scratch of packets through a two-level scene, indexed as their rays (a packet's
    candidates too: from its first ray's entry, at most one a ray)."""

    origins: wp.array(dtype=wp.vec3)  # the rays in the object space of the instance in hand
    directions: wp.array(dtype=wp.vec3)
    tmax: wp.array(dtype=float)  # min(the ray's tmax, its closest hit so far)
    t: wp.array(dtype=float)  # the instance's hits in leaf order
    triangle: wp.array(dtype=int)
    u: wp.array(dtype=float)
    v: wp.array(dtype=float)
    candidates: wp.array(dtype=int)  # the instances to visit, nearest entry first
    entry: wp.array(dtype=float)  # their entries: the least over the packet's rays


def instance_packets(rays: int, device) -> InstancePackets:
    """Room for packets of `rays` rays, numbered from 0."""
    return struct_of_arrays(InstancePackets, rays, device)


@wp.func
def packet_top_ray(s: SceneArrays, origins: wp.array(dtype=wp.vec3),
                   directions: wp.array(dtype=wp.vec3), first: int, last: int) -> TopRay:
    """Rays [first, last) as one TopRay: a box that it enters at t >= 0 (enter_padded_box)
    within [least tmin, greatest tmax] may be entered by some of them, at no smaller t;
    one it misses, none enters. (For t >= 0 every ray's point o + t d lies within
    [o_low + t d_low, o_high + t d_high] and its walls move no faster than the fastest
    ray's, so each wall's test of the bounds passes where any ray's does.)"""
    q = TopRay()
    q.o_low = wp.vec3d(origins[first])
    q.o_high = q.o_low
    d_low = wp.vec3d(directions[first])
    d_high = d_low
    largest = wp.float64(0.0)
    for k in range(first, last):
        o = wp.vec3d(origins[k])
        d = wp.vec3d(directions[k])
        q.o_low = wp.min(q.o_low, o)
        q.o_high = wp.max(q.o_high, o)
        d_low = wp.min(d_low, d)
        d_high = wp.max(d_high, d)
        largest = wp.max(largest, wp.max(wp.max(wp.abs(d[0]), wp.abs(d[1])), wp.abs(d[2])))
    return top_walls(s, q, d_low, d_high, largest)


@wp.func
def packet_candidates(s: SceneArrays, origins: wp.array(dtype=wp.vec3),
                      directions: wp.array(dtype=wp.vec3), tmin: wp.array(dtype=float),
                      tmax: wp.array(dtype=float), first: int, last: int,
                      scratch: InstancePackets) -> int:
    """How many instances some ray of [first, last) may reach (their top-level leaves' boxes
    that the packet's rays as one (packet_top_ray) enter), written from
    scratch.candidates[first] by their entry (a bound below every ray's), nearest first;
    -1 for more than MAX_CANDIDATES or than the rays, or for a negative tmin (the bounds
    hold for t >= 0)."""
    q = packet_top_ray(s, origins, directions, first, last)
    t0 = float(INF)
    t1 = float(-INF)
    for k in range(first, last):
        t0 = wp.min(t0, per_ray(tmin, k))
        t1 = wp.max(t1, per_ray(tmax, k))
    if t0 < 0.0:
        return -1
    stack = NodeStack()
    sp = int(0)
    node = int(0)
    count = int(0)
    room = wp.min(MAX_CANDIDATES, last - first)
    c0 = first
    while node >= 0:
        n = s.top[node]
        t = enter_padded_box(q, n.lo, n.hi, t0, t1)
        node = -1
        if t < INF:
            if n.count > 0:
                for j in range(n.first, n.first + n.count):
                    if count == room:
                        return -1
                    p = c0 + count
                    while p > c0 and scratch.entry[p - 1] > t:
                        scratch.entry[p] = scratch.entry[p - 1]
                        scratch.candidates[p] = scratch.candidates[p - 1]
                        p -= 1
                    scratch.entry[p] = t
                    scratch.candidates[p] = s.top_ids[j]
                    count += 1
            else:
                node = n.first
                stack[sp] = n.first + 1
                sp += 1
        if node < 0 and sp > 0:
            sp -= 1
            node = stack[sp]
    return count


@wp.func
def read_instance_hit(t: wp.array(dtype=float), triangle: wp.array(dtype=int),
                      u: wp.array(dtype=float), v: wp.array(dtype=float),
                      instance: wp.array(dtype=int), k: int) -> InstanceHit:
    """Ray k's hit as the arrays hold it."""
    ih = InstanceHit()
    ih.hit = read_hit(t, triangle, u, v, k)
    ih.instance = instance[k]
    return ih


@wp.func
def write_instance_hit(ih: InstanceHit, k: int, t: wp.array(dtype=float),
                       triangle: wp.array(dtype=int), u: wp.array(dtype=float),
                       v: wp.array(dtype=float), instance: wp.array(dtype=int)):
    """Ray k's hit into the arrays."""
    write_hit(ih.hit, k, t, triangle, u, v)
    instance[k] = ih.instance


@wp.func
def trace_instance_packet(s: SceneArrays, inst: int, origins: wp.array(dtype=wp.vec3),
                          directions: wp.array(dtype=wp.vec3), tmin: wp.array(dtype=float),
                          tmax: wp.array(dtype=float), first: int, last: int,
                          scratch: InstancePackets, out_t: wp.array(dtype=float),
                          out_triangle: wp.array(dtype=int), out_u: wp.array(dtype=float),
                          out_v: wp.array(dtype=float), out_instance: wp.array(dtype=int)):
    """Instance `inst`'s closest hits of rays [first, last), each within its closest hit so
    far, kept where `keep_instance_hit` keeps them."""
    rec = s.instances[inst]
    for k in range(first, last):
        o, d = object_coords(rec, origins[k], directions[k])
        scratch.origins[k] = o
        scratch.directions[k] = d
        scratch.tmax[k] = wp.min(out_t[k], per_ray(tmax, k))
    trace_packet_leaf_order(mesh_view(s.meshes[rec.mesh]), scratch.origins, scratch.directions,
                            tmin, scratch.tmax, first, last, scratch.t, scratch.triangle,
                            scratch.u, scratch.v)
    for k in range(first, last):
        h = read_hit(scratch.t, scratch.triangle, scratch.u, scratch.v, k)
        kept = read_instance_hit(out_t, out_triangle, out_u, out_v, out_instance, k)
        if keep_instance_hit(h, inst, kept):
            write_instance_hit(kept, k, out_t, out_triangle, out_u, out_v, out_instance)


@wp.func
def trace_scene_packet(s: SceneArrays, origins: wp.array(dtype=wp.vec3),
                       directions: wp.array(dtype=wp.vec3), tmin: wp.array(dtype=float),
                       tmax: wp.array(dtype=float), first: int, last: int,
                       scratch: InstancePackets, out_t: wp.array(dtype=float),
                       out_triangle: wp.array(dtype=int), out_u: wp.array(dtype=float),
                       out_v: wp.array(dtype=float), out_instance: wp.array(dtype=int)):
    """The closest hits of rays [first, last) (first a multiple of PACKET, last - first at
    most PACKET) as `traverse_scene` gives them: refined, the mesh's triangle index, the
    instance (-1 on a miss)."""
    count = packet_candidates(s, origins, directions, tmin, tmax, first, last, scratch)
    for k in range(first, last):
        ih = InstanceHit()
        no_instance_hit(ih)
        if count < 0:  # too many instances for a packet
            ih = traverse_scene(s, origins[k], directions[k], per_ray(tmin, k), per_ray(tmax, k),
                                False)
        write_instance_hit(ih, k, out_t, out_triangle, out_u, out_v, out_instance)
    for c in range(count):
        # an instance that every ray's closest hit so far lies before is skipped
        reach = float(-INF)
        for k in range(first, last):
            reach = wp.max(reach, wp.min(out_t[k], per_ray(tmax, k)))
        if scratch.entry[first + c] <= reach:
            trace_instance_packet(s, scratch.candidates[first + c], origins, directions, tmin, tmax,
                                  first, last, scratch, out_t, out_triangle, out_u, out_v,
                                  out_instance)
    if count > 0:
        for k in range(first, last):
            kept = read_instance_hit(out_t, out_triangle, out_u, out_v, out_instance, k)
            ih = finish_instance_hit(s, origins[k], directions[k], per_ray(tmin, k),
                                     per_ray(tmax, k), kept, False)
            write_instance_hit(ih, k, out_t, out_triangle, out_u, out_v, out_instance)


@wp.func
def trace_scene_group(s: SceneArrays, origins: wp.array(dtype=wp.vec3),
                      directions: wp.array(dtype=wp.vec3), tmin: wp.array(dtype=float),
                      tmax: wp.array(dtype=float), first: int, last: int,
                      scratch: InstancePackets, out_triangle: wp.array(dtype=int)):
    """Whether each any-hit ray of [first, last) (at most PACKET) meets a triangle in
    [tmin, tmax]: out_triangle[k] a triangle of the mesh of an instance it meets, else -1.
    The instances that some ray may reach (packet_candidates), nearest first, each traced
    as one group of the rays not yet blocked, in its object space; ray by ray where there
    are too many."""
    count = packet_candidates(s, origins, directions, tmin, tmax, first, last, scratch)
    for k in range(first, last):
        out_triangle[k] = -1
        if count < 0:
            ih = traverse_scene(s, origins[k], directions[k], per_ray(tmin, k), per_ray(tmax, k),
                                True)
            out_triangle[k] = ih.hit.triangle
    for c in range(count):
        rec = s.instances[scratch.candidates[first + c]]
        open_rays = int(0)
        for k in range(first, last):  # every ray set: a group declines a non-finite one
            o, d = object_coords(rec, origins[k], directions[k])
            scratch.origins[k] = o
            scratch.directions[k] = d
            scratch.tmax[k] = -1.0  # blocked: an empty range below tmin (>= 0 here)
            if out_triangle[k] < 0:
                scratch.tmax[k] = per_ray(tmax, k)
                open_rays += 1
        if open_rays == 0:
            return
        trace_occlusion_group(mesh_view(s.meshes[rec.mesh]), scratch.origins, scratch.directions,
                              tmin, scratch.tmax, first, last, scratch.t, scratch.triangle,
                              scratch.u, scratch.v, True)
        for k in range(first, last):
            if out_triangle[k] < 0:
                out_triangle[k] = scratch.triangle[k]


@wp.kernel
def scene_packet_kernel(
    s: SceneArrays,
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    tmin: wp.array(dtype=float),  # per ray, or one value for all
    tmax: wp.array(dtype=float),
    # InstancePackets' arrays (indexed as the rays), one by one
    scratch_origins: wp.array(dtype=wp.vec3),
    scratch_directions: wp.array(dtype=wp.vec3),
    scratch_tmax: wp.array(dtype=float),
    scratch_t: wp.array(dtype=float),
    scratch_triangle: wp.array(dtype=int),
    scratch_u: wp.array(dtype=float),
    scratch_v: wp.array(dtype=float),
    scratch_candidates: wp.array(dtype=int),
    scratch_entry: wp.array(dtype=float),
    out_t: wp.array(dtype=float),
    out_triangle: wp.array(dtype=int),
    out_u: wp.array(dtype=float),
    out_v: wp.array(dtype=float),
    out_instance: wp.array(dtype=int),
    invalid: wp.array(dtype=int),  # set to 1 where a ray is one as_rays refuses
    claims: Claims,  # chunks of a multiple of PACKET rays
):
    items = claimed_items(claims, wp.tid())
    flag_invalid_rays(origins, directions, items[0], items[1], invalid)
    scratch = InstancePackets()
    scratch.origins = scratch_origins
    scratch.directions = scratch_directions
    scratch.tmax = scratch_tmax
    scratch.t = scratch_t
    scratch.triangle = scratch_triangle
    scratch.u = scratch_u
    scratch.v = scratch_v
    scratch.candidates = scratch_candidates
    scratch.entry = scratch_entry
    for i in range(items[0], items[1], PACKET):
        trace_scene_packet(s, origins, directions, tmin, tmax, i, wp.min(i + PACKET, items[1]),
                           scratch, out_t, out_triangle, out_u, out_v, out_instance)


def scratch_arrays(scratch: InstancePackets) -> list:
    """scene_packet_kernel's scratch arguments, in order."""
    return [scratch.origins, scratch.directions, scratch.tmax, scratch.t, scratch.triangle,
            scratch.u, scratch.v, scratch.candidates, scratch.entry]


def scene_packets_apply(device) -> bool:
    """Whether a scene's closest-hit rays go through scene_packet_kernel: on a CPU with the
    SIMD traversal of width 8 (meshes of other widths are traced ray by ray in it)."""
    return device.is_cpu and simd_support(device)[0] == 8


WARP_MODULES = (scene_packet_kernel.module,)  # this module's kernels (core.launch.load_modules)
