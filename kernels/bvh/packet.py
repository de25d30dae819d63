"""Closest-hit rays traced in packets of coherent rays (wide_packet.h: ranged packet
traversal of the wide tree on an AVX2 CPU); a packet the packet traversal declines, or any
packet on other devices, is traced ray by ray. The hits are the single-ray traversal's
(wide_packet.h's header says where a triangle may differ at the same distance).
"""

from __future__ import annotations

import warp as wp

from ..core.claim import Claims, claimed_items
from ..core.compile_options import MODULE_OPTIONS
from ..core.ray import FAR_WIDEN, Hit, make_ray, per_ray
from .leaf import finish_hit
from .node import BvhArrays
from .traversal import traverse_leaf_order
from .wide import NATIVE_LAYOUT
from .wide_traversal import SIMD_GUARD, native_source, simd_support

wp.set_module_options(MODULE_OPTIONS)

PACKET = 64  # rays per packet: a camera's 8 x 8 tile, or a run of 64 pixels of a row
COHERENT_SPREAD = 0.5  # most spread of a packet's unit directions on an axis (wide_packet.h)

_SOURCE = native_source("wide_packet.h")
_LAYOUT = "".join(f"    constexpr int {name} = {int(value)};\n"
                  for name, value in {**NATIVE_LAYOUT, "PACKET": PACKET}.items())
_LAYOUT += f"    constexpr float COHERENT_SPREAD = {COHERENT_SPREAD}f;\n"


@wp.func_native(f"{SIMD_GUARD}\n{_LAYOUT}{_SOURCE}#else\n    return 0;\n#endif\n")
def traverse_packet_simd(wide: wp.array(dtype=float), blocks: wp.array(dtype=float),
                         width_arg: int, origins: wp.array(dtype=wp.vec3),
                         directions: wp.array(dtype=wp.vec3), tmin: wp.array(dtype=float),
                         tmax: wp.array(dtype=float), first_ray: int, last_ray: int,
                         widen: float, out_t: wp.array(dtype=float),
                         out_triangle: wp.array(dtype=int), out_u: wp.array(dtype=float),
                         out_v: wp.array(dtype=float)) -> int:
    """Rays [first_ray, last_ray) as one packet: each closest hit in [tmin, tmax] (t, leaf
    position, u, v; t inf and -1 on a miss) into the outputs; 0 where the packet traversal
    does not apply (wide_packet.h's header), the outputs untouched."""
    ...


@wp.func
def read_hit(t: wp.array(dtype=float), triangle: wp.array(dtype=int), u: wp.array(dtype=float),
             v: wp.array(dtype=float), k: int) -> Hit:
    """Ray k's hit as the arrays hold it."""
    h = Hit()
    h.t = t[k]
    h.triangle = triangle[k]
    h.u = u[k]
    h.v = v[k]
    return h


@wp.func
def write_hit(h: Hit, k: int, t: wp.array(dtype=float), triangle: wp.array(dtype=int),
              u: wp.array(dtype=float), v: wp.array(dtype=float)):
    """Ray k's hit into the arrays."""
    t[k] = h.t
    triangle[k] = h.triangle
    u[k] = h.u
    v[k] = h.v


@wp.func
def trace_packet_leaf_order(bvh: BvhArrays, origins: wp.array(dtype=wp.vec3),
                            directions: wp.array(dtype=wp.vec3), tmin: wp.array(dtype=float),
                            tmax: wp.array(dtype=float), first: int, last: int,
                            out_t: wp.array(dtype=float), out_triangle: wp.array(dtype=int),
                            out_u: wp.array(dtype=float), out_v: wp.array(dtype=float)):
    """The closest hits of rays [first, last) as `traverse_leaf_order` gives them (leaf
    positions, unrefined): as one packet where the packet traversal takes them, else ray by
    ray."""
    packed = traverse_packet_simd(bvh.wide, bvh.blocks, bvh.width, origins, directions, tmin,
                                  tmax, first, last, FAR_WIDEN, out_t, out_triangle, out_u,
                                  out_v)
    if packed == 0:
        for k in range(first, last):
            h = traverse_leaf_order(bvh, make_ray(origins[k], directions[k]), per_ray(tmin, k),
                                    per_ray(tmax, k), False)
            write_hit(h, k, out_t, out_triangle, out_u, out_v)


@wp.func
def trace_packet_hits(bvh: BvhArrays, origins: wp.array(dtype=wp.vec3),
                      directions: wp.array(dtype=wp.vec3), tmin: wp.array(dtype=float),
                      tmax: wp.array(dtype=float), first: int, last: int,
                      out_t: wp.array(dtype=float), out_triangle: wp.array(dtype=int),
                      out_u: wp.array(dtype=float), out_v: wp.array(dtype=float)):
    """The closest hits of rays [first, last) as `traverse` gives them (refined, the
    caller's triangle index)."""
    trace_packet_leaf_order(bvh, origins, directions, tmin, tmax, first, last, out_t,
                            out_triangle, out_u, out_v)
    for k in range(first, last):
        h = finish_hit(bvh, make_ray(origins[k], directions[k]), per_ray(tmin, k),
                       per_ray(tmax, k), read_hit(out_t, out_triangle, out_u, out_v, k))
        write_hit(h, k, out_t, out_triangle, out_u, out_v)


@wp.kernel
def packet_trace_kernel(
    bvh: BvhArrays,
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    tmin: wp.array(dtype=float),  # per ray, or one value for all
    tmax: wp.array(dtype=float),
    out_t: wp.array(dtype=float),
    out_triangle: wp.array(dtype=int),
    out_u: wp.array(dtype=float),
    out_v: wp.array(dtype=float),
    claims: Claims,  # chunks of a multiple of PACKET rays
):
    items = claimed_items(claims, wp.tid())
    for i in range(items[0], items[1], PACKET):
        trace_packet_hits(bvh, origins, directions, tmin, tmax, i, wp.min(i + PACKET, items[1]),
                          out_t, out_triangle, out_u, out_v)


def packets_apply(bvh) -> bool:
    """Whether `trace` sends closest-hit rays through packet_trace_kernel: a CPU with the
    SIMD traversal and a tree of width 8 (elsewhere every packet would be declined)."""
    return bvh.device.is_cpu and bvh.stats.width == 8 and simd_support(bvh.device)[0] == 8
