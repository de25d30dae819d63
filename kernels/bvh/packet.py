"""Rays traced together through the wide tree on an AVX2 CPU: closest-hit rays in packets
of coherent rays (wide_packet.h: ranged packet traversal), any-hit rays in groups of 64
(wide_occlusion.h: a masked packet, each ray's first hit as its own traversal finds it). A
packet or group the native traversal declines, or any on other devices, is traced ray by
ray. The hits are the single-ray traversal's (wide_packet.h's header says where a closest
hit's triangle may differ at the same distance).
"""

from __future__ import annotations

import warp as wp

from ..core.claim import Claims, claimed_items
from ..core.compile_options import MODULE_OPTIONS
from ..core.ray import FAR_WIDEN, Hit, flag_invalid_rays, make_ray, per_ray
from .leaf import finish_hit, leaf_position
from .node import BvhArrays
from .traversal import traverse, traverse_leaf_order
from .wide import NATIVE_LAYOUT
from .wide_traversal import SIMD_GUARD, native_source, simd_support

wp.set_module_options(MODULE_OPTIONS)

PACKET = 64  # rays per packet: a camera's 8 x 8 tile, or a run of 64 pixels of a row
GROUP = 64  # any-hit rays per group (wide_occlusion.h): one bit each of a 64-bit mask
assert GROUP == PACKET  # packet_trace_kernel steps over both in runs of one size
COHERENT_SPREAD = 0.5  # most spread of a packet's unit directions on an axis (wide_packet.h)


def _native(name: str, constants: dict[str, int]) -> str:
    """The body of a `wp.func_native` running native text `name` (wide_simd.h's header
    says how): where SIMD_GUARD holds, the constants, then the text; 0 elsewhere."""
    layout = "".join(f"    constexpr int {k} = {int(v)};\n" for k, v in constants.items())
    layout += f"    constexpr float COHERENT_SPREAD = {COHERENT_SPREAD}f;\n"
    return f"{SIMD_GUARD}\n{layout}{native_source(name)}#else\n    return 0;\n#endif\n"


@wp.func_native(_native("wide_packet.h", {**NATIVE_LAYOUT, "PACKET": PACKET}))
def traverse_packet_simd(wide: wp.array(dtype=float), blocks: wp.array(dtype=float),
                         width_arg: int, origins: wp.array(dtype=wp.vec3),
                         directions: wp.array(dtype=wp.vec3), tmin: wp.array(dtype=float),
                         tmax: wp.array(dtype=float), first_ray: int, last_ray: int,
                         widen: float, tri_ids: wp.array(dtype=int), finish: int,
                         out_t: wp.array(dtype=float), out_triangle: wp.array(dtype=int),
                         out_u: wp.array(dtype=float), out_v: wp.array(dtype=float)) -> int:
    """Rays [first_ray, last_ray) as one packet: each closest hit in [tmin, tmax] into the
    outputs (t inf and -1 on a miss), finished as `leaf.finish_hit` does where `finish` is
    1, else as found (t, u, v unrefined, the hit's reference: leaf.py); 0 where the packet
    traversal does not apply (wide_packet.h's header), the outputs untouched."""
    ...


@wp.func_native(_native("wide_occlusion.h", {**NATIVE_LAYOUT, "GROUP": GROUP}))
def traverse_occlusion_simd(wide: wp.array(dtype=float), blocks: wp.array(dtype=float),
                            width_arg: int, origins: wp.array(dtype=wp.vec3),
                            directions: wp.array(dtype=wp.vec3), tmin: wp.array(dtype=float),
                            tmax: wp.array(dtype=float), first_ray: int, last_ray: int,
                            widen: float, out_t: wp.array(dtype=float),
                            out_triangle: wp.array(dtype=int), out_u: wp.array(dtype=float),
                            out_v: wp.array(dtype=float)) -> int:
    """Rays [first_ray, last_ray) as one group of any-hit rays: each ray's first hit found
    (t, leaf position, u, v; t inf and -1 on a miss) into the outputs, the same as its own
    traversal finds; 0 where the group traversal does not apply (wide_occlusion.h's
    header), the outputs untouched."""
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
def trace_packet(bvh: BvhArrays, origins: wp.array(dtype=wp.vec3),
                 directions: wp.array(dtype=wp.vec3), tmin: wp.array(dtype=float),
                 tmax: wp.array(dtype=float), first: int, last: int, finish: bool,
                 out_t: wp.array(dtype=float), out_triangle: wp.array(dtype=int),
                 out_u: wp.array(dtype=float), out_v: wp.array(dtype=float)):
    """The closest hits of rays [first, last): as one packet where the packet traversal
    takes them, else ray by ray; as `traverse` gives them (`finish`) or as
    `traverse_leaf_order` does."""
    packed = traverse_packet_simd(bvh.wide, bvh.blocks, bvh.width, origins, directions, tmin,
                                  tmax, first, last, FAR_WIDEN, bvh.tri_ids,
                                  wp.where(finish, 1, 0), out_t, out_triangle, out_u, out_v)
    if packed == 0:
        for k in range(first, last):
            r = make_ray(origins[k], directions[k])
            h = traverse_leaf_order(bvh, r, per_ray(tmin, k), per_ray(tmax, k), False)
            if finish:
                h = finish_hit(bvh, r, per_ray(tmin, k), per_ray(tmax, k), h)
            write_hit(h, k, out_t, out_triangle, out_u, out_v)


@wp.func
def trace_packet_leaf_order(bvh: BvhArrays, origins: wp.array(dtype=wp.vec3),
                            directions: wp.array(dtype=wp.vec3), tmin: wp.array(dtype=float),
                            tmax: wp.array(dtype=float), first: int, last: int,
                            out_t: wp.array(dtype=float), out_triangle: wp.array(dtype=int),
                            out_u: wp.array(dtype=float), out_v: wp.array(dtype=float)):
    """`trace_packet`'s hits as found (hit references, unrefined)."""
    trace_packet(bvh, origins, directions, tmin, tmax, first, last, False, out_t,
                 out_triangle, out_u, out_v)


@wp.func
def trace_packet_hits(bvh: BvhArrays, origins: wp.array(dtype=wp.vec3),
                      directions: wp.array(dtype=wp.vec3), tmin: wp.array(dtype=float),
                      tmax: wp.array(dtype=float), first: int, last: int,
                      out_t: wp.array(dtype=float), out_triangle: wp.array(dtype=int),
                      out_u: wp.array(dtype=float), out_v: wp.array(dtype=float)):
    """`trace_packet`'s hits finished (refined, the caller's triangle index)."""
    trace_packet(bvh, origins, directions, tmin, tmax, first, last, True, out_t,
                 out_triangle, out_u, out_v)


@wp.func(inline=False)  # inlined, it made the film kernel around it 1.3x slower
def any_hit_ray(bvh: BvhArrays, origins: wp.array(dtype=wp.vec3),
                directions: wp.array(dtype=wp.vec3), tmin: wp.array(dtype=float),
                tmax: wp.array(dtype=float), k: int, find_any: bool) -> Hit:
    """Ray k's first hit found, by its own traversal (a group the group traversal declined)."""
    return traverse(bvh, make_ray(origins[k], directions[k]), per_ray(tmin, k), per_ray(tmax, k),
                    find_any)


@wp.func
def trace_occlusion_group(bvh: BvhArrays, origins: wp.array(dtype=wp.vec3),
                          directions: wp.array(dtype=wp.vec3), tmin: wp.array(dtype=float),
                          tmax: wp.array(dtype=float), first: int, last: int,
                          out_t: wp.array(dtype=float), out_triangle: wp.array(dtype=int),
                          out_u: wp.array(dtype=float), out_v: wp.array(dtype=float),
                          find_any: bool):
    """The first hits of any-hit rays [first, last) as `traverse` gives them (the caller's
    triangle index): as one group where the group traversal takes them, else ray by ray
    (`find_any`: True, passed as a run-time value, as traverse asks)."""
    grouped = traverse_occlusion_simd(bvh.wide, bvh.blocks, bvh.width, origins, directions,
                                      tmin, tmax, first, last, FAR_WIDEN, out_t, out_triangle,
                                      out_u, out_v)
    for k in range(first, last):
        if grouped == 0:
            write_hit(any_hit_ray(bvh, origins, directions, tmin, tmax, k, find_any), k, out_t,
                      out_triangle, out_u, out_v)
        elif out_triangle[k] >= 0:
            out_triangle[k] = bvh.tri_ids[leaf_position(bvh, out_triangle[k])]


@wp.kernel
def packet_trace_kernel(
    bvh: BvhArrays,
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    tmin: wp.array(dtype=float),  # per ray, or one value for all
    tmax: wp.array(dtype=float),
    find_any: int,  # 0: closest hits in packets; 1: any hits in groups
    out_t: wp.array(dtype=float),
    out_triangle: wp.array(dtype=int),
    out_u: wp.array(dtype=float),
    out_v: wp.array(dtype=float),
    invalid: wp.array(dtype=int),  # set to 1 where a ray is one as_rays refuses
    claims: Claims,  # chunks of a multiple of PACKET (= GROUP) rays
):
    items = claimed_items(claims, wp.tid())
    flag_invalid_rays(origins, directions, items[0], items[1], invalid)
    for i in range(items[0], items[1], PACKET):
        last = wp.min(i + PACKET, items[1])
        if find_any != 0:
            trace_occlusion_group(bvh, origins, directions, tmin, tmax, i, last, out_t,
                                  out_triangle, out_u, out_v, find_any != 0)
        else:
            trace_packet_hits(bvh, origins, directions, tmin, tmax, i, last, out_t,
                              out_triangle, out_u, out_v)


def packets_apply(bvh) -> bool:
    """Whether `trace` sends its rays through packet_trace_kernel (closest hits in packets,
    any hits in groups): a CPU with the SIMD traversal and a tree of width 8
    (elsewhere every packet and group would be declined)."""
    return bvh.device.is_cpu and bvh.stats.width == 8 and simd_support(bvh.device)[0] == 8
