"""What traces the render's rays: per tracer (a mesh's BVH: `MeshTracer`; a two-level scene:
`SceneArrays`) the closest surface of a primary ray and whether an occlusion ray is
blocked, as Warp overloads, so that the render's kernels are generic over the tracer; and
the occlusion rounds on the host, through the BVH or scene, or with the task-pool DACRT
(`engine="dacrt"`: the same rays, closest hit within the AO distance).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp

from scenesort.ao_options import AO_OPTIONS, AoOptions

from ..bvh.api import Bvh
from ..bvh.node import BvhArrays
from ..bvh.packet import GROUP, PACKET, trace_occlusion_group, trace_packet_hits
from ..bvh.traversal import closest_hit, traverse
from ..bvh.wide_traversal import simd_lanes
from ..core.claim import Claims, claimed_items
from ..core.compile_options import MODULE_OPTIONS
from ..core.device_arrays import struct_of_arrays
from ..core.launch import PARTS_PER_THREAD, part_launcher, run_parts
from ..core.mesh import DeviceMesh, Shading
from ..core.ray import make_ray
from ..dacrt.api import dacrt_trace_mesh
from ..scene.api import Scene
from ..scene.packet import (
    InstancePackets,
    instance_packets,
    read_instance_hit,
    trace_scene_group,
    trace_scene_packet,
)
from ..scene.top import SceneArrays, SceneShading, traverse_scene
from .adaptive import RoundTracer
from .sampling import SAMPLERS, cosine_direction, pixel_key
from .surface import (
    PrimaryHits,
    Surface,
    instance_surface,
    occlusion_origin,
    surface,
    terminator_amount,
)

wp.set_module_options(MODULE_OPTIONS)

PART_RAYS = 4096  # fewest occlusion rays worth a host thread of their own
LAUNCH_RAYS = 1 << 30  # most rays per launch (a launch's thread index is int32)


@wp.struct
class MeshTracer:
    """A single mesh's BVH and triangles: what the render kernels trace and shade."""

    bvh: BvhArrays
    vertices: wp.array(dtype=wp.vec3)
    indices: wp.array(dtype=wp.vec3i)


@wp.func
def closest_surface(g: MeshTracer, shading: Shading, o: wp.vec3, d: wp.vec3, tmin: float,
                    tmax: float):
    """(Surface, True) of the closest hit in [tmin, tmax], or (anything, False)."""
    h = closest_hit(g.bvh, o, d, tmin, tmax)
    if h.triangle >= 0:
        return surface(g.vertices, g.indices, shading, d, h.triangle, h.u, h.v, True), True
    return Surface(), False


@wp.func  # a Warp overload of the one above (by the first argument's type)
def closest_surface(g: SceneArrays, shading: SceneShading, o: wp.vec3, d: wp.vec3,  # noqa: F811
                    tmin: float, tmax: float):
    """`closest_surface` through a two-level scene."""
    ih = traverse_scene(g, o, d, tmin, tmax, False)
    if ih.instance >= 0:
        return instance_surface(g, shading, d, ih, True), True
    return Surface(), False


@wp.struct
class GroupRays:
    """A host thread's occlusion rays of one group (bvh/packet.py's GROUP), indexed from
    each part's first entry: the sample each belongs to, its range and its first hit (any
    hit: occluded where triangle >= 0)."""

    origins: wp.array(dtype=wp.vec3)
    directions: wp.array(dtype=wp.vec3)
    tmin: wp.array(dtype=float)
    tmax: wp.array(dtype=float)
    sample: wp.array(dtype=int)
    t: wp.array(dtype=float)
    triangle: wp.array(dtype=int)
    u: wp.array(dtype=float)
    v: wp.array(dtype=float)
    scene: InstancePackets  # a two-level scene's scratch (scene/packet.py)


def group_rays(parts: int, scene: bool, device) -> GroupRays:
    """Room for one group per part (with a two-level scene's scratch if `scene`)."""
    rays = struct_of_arrays(GroupRays, parts * GROUP, device)
    rays.scene = instance_packets(parts * GROUP if scene else 0, device)
    return rays


@wp.func
def add_group_ray(rays: GroupRays, k: int, o: wp.vec3, w: wp.vec3, distance: float,
                  sample: int):
    """Ray k of the group: sample `sample`'s occlusion ray from o along w."""
    rays.origins[k] = o
    rays.directions[k] = w
    rays.tmin[k] = 0.0
    rays.tmax[k] = distance
    rays.sample[k] = sample


@wp.func
def occluded_group(g: BvhArrays, rays: GroupRays, first: int, last: int):
    """Traces rays [first, last) of `rays` for any hit: those blocked get triangle >= 0. On
    an AVX2 CPU they go through the wide tree as one group (bvh/packet.py)."""
    trace_occlusion_group(g, rays.origins, rays.directions, rays.tmin, rays.tmax, first, last,
                          rays.t, rays.triangle, rays.u, rays.v, True)


@wp.func  # a Warp overload of the one above: through a two-level scene (scene/packet.py)
def occluded_group(g: SceneArrays, rays: GroupRays, first: int, last: int):  # noqa: F811
    trace_scene_group(g, rays.origins, rays.directions, rays.tmin, rays.tmax, first, last,
                      rays.scene, rays.triangle)


@wp.func
def open_sample(i: int, mid: int, quarter: int) -> wp.vec3i:
    """Sample i's counts when it is open (its value 1): all, below `mid`, below `quarter`
    (<= mid)."""
    return wp.vec3i(1, wp.where(i < mid, 1, 0), wp.where(i < quarter and i < mid, 1, 0))


@wp.struct
class PacketRays:
    """A host thread's rays of one packet and their closest hits (bvh/packet.py,
    scene/packet.py), indexed from each part's first entry: camera rays that the CPU traces
    together."""

    origins: wp.array(dtype=wp.vec3)
    directions: wp.array(dtype=wp.vec3)
    tmin: wp.array(dtype=float)
    tmax: wp.array(dtype=float)
    t: wp.array(dtype=float)
    triangle: wp.array(dtype=int)
    u: wp.array(dtype=float)
    v: wp.array(dtype=float)
    instance: wp.array(dtype=int)  # a two-level scene's: the hit instance
    scene: InstancePackets  # a two-level scene's scratch
    points: wp.array(dtype=wp.vec2)  # the film's: each sample's occlusion-direction point


def packet_rays(parts: int, scene: bool, device) -> PacketRays:
    """Room for one packet per part (with a two-level scene's scratch if `scene`)."""
    rays = struct_of_arrays(PacketRays, parts * PACKET, device)
    rays.scene = instance_packets(parts * PACKET if scene else 0, device)
    return rays


@wp.func
def packet_hit_surface(g: MeshTracer, shading: Shading, rays: PacketRays, k: int,
                       lifted: bool):
    """(Surface, True) of ray k of `rays`, traced, or (anything, False) (`lifted`: see
    surface_at)."""
    if rays.triangle[k] >= 0:
        return surface(g.vertices, g.indices, shading, rays.directions[k], rays.triangle[k],
                       rays.u[k], rays.v[k], lifted), True
    return Surface(), False


@wp.func  # a Warp overload of the one above: through a two-level scene
def packet_hit_surface(g: SceneArrays, shading: SceneShading, rays: PacketRays,  # noqa: F811
                       k: int, lifted: bool):
    if rays.instance[k] >= 0:
        ih = read_instance_hit(rays.t, rays.triangle, rays.u, rays.v, rays.instance, k)
        return instance_surface(g, shading, rays.directions[k], ih, lifted), True
    return Surface(), False


@wp.func
def packet_closest(g: MeshTracer, rays: PacketRays, first: int, last: int):
    """The closest hits of rays [first, last) of `rays` into it (trace_packet_hits; t inf
    and triangle -1 on a miss)."""
    trace_packet_hits(g.bvh, rays.origins, rays.directions, rays.tmin, rays.tmax, first,
                      last, rays.t, rays.triangle, rays.u, rays.v)


@wp.func  # a Warp overload of the one above: through a two-level scene (scene/packet.py)
def packet_closest(g: SceneArrays, rays: PacketRays, first: int, last: int):  # noqa: F811
    trace_scene_packet(g, rays.origins, rays.directions, rays.tmin, rays.tmax, first, last,
                       rays.scene, rays.t, rays.triangle, rays.u, rays.v, rays.instance)


@wp.func
def packet_surface(g: Any, shading: Any, rays: PacketRays, first: int, k: int, last: int):
    """`closest_surface` of ray k of rays [first, last) of `rays`, its lift left to
    packet_occlusion_origin; at k == first the closest hits of them all are traced
    (packet_closest), into `rays`."""
    if k == first:
        packet_closest(g, rays, first, last)
    return packet_hit_surface(g, shading, rays, k, False)


@wp.func
def closest_t(g: SceneArrays, o: wp.vec3, d: wp.vec3, tmin: float, tmax: float) -> float:
    """The distance of a two-level scene's closest hit in [tmin, tmax] (inf on a miss)."""
    ih = traverse_scene(g, o, d, tmin, tmax, False)
    t = float(wp.inf)
    if ih.instance >= 0:
        t = ih.hit.t
    return t


@wp.func
def packet_occlusion_origin(g: Any, shading: Any, rays: PacketRays, k: int, s: Surface,
                            w: wp.vec3) -> wp.vec3:
    """`occlusion_origin` toward w of packet ray k's surface `s` (packet_surface's, made
    without its lift): the lift is made only where terminator_amount moves the origin, for
    directions near the terminator (a few percent of a film's samples; a smooth surface
    costs 60 ns with its lift, 25 ns without)."""
    if terminator_amount(s.n, s.ng, w, s.cutoff) > 0.0:
        lifted, hit = packet_hit_surface(g, shading, rays, k, True)
        return occlusion_origin(lifted, w)
    return s.point


@wp.func
def occluded(g: BvhArrays, o: wp.vec3, w: wp.vec3, distance: float, find_any: bool) -> bool:
    """Whether a triangle lies within `distance` along w from o."""
    return traverse(g, make_ray(o, w), 0.0, distance, find_any).triangle >= 0


@wp.func  # a Warp overload of the one above
def occluded(g: SceneArrays, o: wp.vec3, w: wp.vec3, distance: float,  # noqa: F811
             find_any: bool) -> bool:
    """`occluded` in a two-level scene."""
    return traverse_scene(g, o, w, 0.0, distance, find_any).instance >= 0


@wp.kernel
def primary_kernel(
    tracer: Any,  # MeshTracer or SceneArrays
    shading: Any,  # Shading or SceneShading
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    tmin: wp.array(dtype=float),
    tmax: wp.array(dtype=float),
    out_surface: wp.array(dtype=Surface),
    out_hit: wp.array(dtype=int),
    claims: Claims,
):
    items = claimed_items(claims, wp.tid())
    for i in range(items[0], items[1]):
        s, hit = closest_surface(tracer, shading, origins[i], directions[i], tmin[i], tmax[i])
        out_hit[i] = 0
        if hit:
            out_surface[i] = s
            out_hit[i] = 1


@wp.kernel
def surface_kernel(
    vertices: wp.array(dtype=wp.vec3),
    indices: wp.array(dtype=wp.vec3i),
    shading: Shading,
    directions: wp.array(dtype=wp.vec3),
    triangle: wp.array(dtype=int),
    u: wp.array(dtype=float),
    v: wp.array(dtype=float),
    out_surface: wp.array(dtype=Surface),
):
    """Surfaces of hits found by another tracer (engine="dacrt")."""
    i = wp.tid()
    out_surface[i] = surface(vertices, indices, shading, directions[i], triangle[i], u[i], v[i],
                             True)


@wp.kernel
def occlusion_kernel(
    bvh: Any,  # BvhArrays or SceneArrays
    surfaces: wp.array(dtype=Surface),
    pixels: wp.array(dtype=int),
    active: wp.array(dtype=int),  # hit-pixel index of each slot of this round
    slot0: int,  # the first slot of this launch
    first: int,  # the first sample index of this round (the same for every slot)
    count: int,  # samples per slot this round
    span: int,  # samples per kernel thread: count on CPU, 1 on CUDA (a divisor of count)
    sampler: int,
    seed: int,
    distance: float,
    find_any: int,  # always 1; see below
    mid: int,  # out_open_mid counts the open samples with index below this (absolute)
    quarter: int,  # out_open_quarter: those below this
    group: GroupRays,  # one group per part (CPU)
    group0: int,  # this launch's group in `group`
    out_open: wp.array(dtype=int),  # per slot: open samples (accumulated)
    out_open_mid: wp.array(dtype=int),
    out_open_quarter: wp.array(dtype=int),
):
    # `span` samples of one slot per thread, slot-major. On CPU a thread takes a slot's
    # samples (the slot's reads, key and frame once, not per ray); on CUDA one ray each.
    # A slot never straddles two launches: the plain read-modify-write adds below need no
    # atomics (Warp's are not atomic on CPU; on CUDA `+=` is an atomic add).
    # Cosine-weighted estimator (PBR 4th ed. 13.6.3 / A.5.3): each sample is V(p, w).
    t = wp.tid()
    threads_per_slot = count / span
    j = slot0 + t / threads_per_slot
    s0 = first + (t % threads_per_slot) * span
    k = active[j]
    hit = surfaces[k]
    key = pixel_key(pixels[k], seed)
    opened = wp.vec3i(0, 0, 0)  # open samples: all, below mid, below quarter
    m = int(0)
    for s in range(s0, s0 + span):
        w = cosine_direction(hit.n, sampler, key, s)
        o = occlusion_origin(hit, w)
        if simd_lanes() > 0:  # the slot's rays in groups (from one point: bvh/wide_occlusion.h)
            add_group_ray(group, group0 + m, o, w, distance, s)
            m += 1
            if m == GROUP or s == s0 + span - 1:
                occluded_group(bvh, group, group0, group0 + m)
                for g in range(group0, group0 + m):
                    if group.triangle[g] < 0:
                        opened += open_sample(group.sample[g], mid, quarter)
                m = 0
        # traverse() with a run-time any-hit flag, as trace_kernel calls it: measured 25-30%
        # faster on CPU than bvh_trace.any_hit, whose flag is the literal True.
        elif not occluded(bvh, o, w, distance, find_any != 0):
            opened += open_sample(s, mid, quarter)
    if opened[0] > 0:
        out_open[j] += opened[0]
        out_open_mid[j] += opened[1]
        out_open_quarter[j] += opened[2]


@wp.kernel
def rays_kernel(
    surfaces: wp.array(dtype=Surface),
    pixels: wp.array(dtype=int),
    first: int,
    count: int,
    sampler: int,
    seed: int,
    out_origin: wp.array(dtype=wp.vec3),
    out_dir: wp.array(dtype=wp.vec3),
):
    i, s = wp.tid()
    key = pixel_key(pixels[i], seed)
    hit = surfaces[i]
    w = cosine_direction(hit.n, sampler, key, first + s)
    out_origin[i * count + s] = occlusion_origin(hit, w)
    out_dir[i * count + s] = w


for _tracer, _shading in ((MeshTracer, Shading), (SceneArrays, SceneShading)):
    wp.overload(primary_kernel, {"tracer": _tracer, "shading": _shading})
wp.overload(occlusion_kernel, {"bvh": BvhArrays})
wp.overload(occlusion_kernel, {"bvh": SceneArrays})


@wp.kernel
def gather_surfaces_kernel(src: wp.array(dtype=Surface), sel: wp.array(dtype=int),
                           dst: wp.array(dtype=Surface)):
    i = wp.tid()
    dst[i] = src[sel[i]]


# --- host side ---------------------------------------------------------------------------


def gather_surfaces(surfaces: wp.array, select: np.ndarray) -> wp.array:
    """The surfaces `select` indexes, on their device."""
    device = surfaces.device
    out = wp.empty(len(select), dtype=Surface, device=device)
    if len(select):
        sel = wp.array(np.asarray(select, np.int32), dtype=int, device=device)
        wp.launch(gather_surfaces_kernel, dim=len(select), inputs=[surfaces, sel, out],
                  device=device)
    return out


def scene_mesh(bvh: Bvh) -> DeviceMesh:
    """The BVH's mesh on the device (made here for a `Bvh` put together by hand)."""
    if bvh.mesh is None:
        bvh.mesh = DeviceMesh(bvh.vertices, bvh.indices, bvh.device)
    return bvh.mesh


def check_tracer(bvh: Any, engine: str) -> None:
    """What render_ao traces through: a Bvh with either engine, a Scene with engine="bvh"."""
    if isinstance(bvh, Scene):
        if engine == "dacrt":
            raise ValueError('engine="dacrt" traces one world-space triangle list; a two-level '
                             'Scene is traced with engine="bvh" (or flatten it into one mesh)')
    elif not isinstance(bvh, Bvh):
        raise ValueError(f"render_ao takes a Bvh (build_bvh) or a Scene (build_scene), got "
                         f"{type(bvh).__name__}")


def occlusion_tracer(bvh: Bvh | Scene, hits: PrimaryHits, opts: AoOptions, dist: float,
                     nthreads: int) -> RoundTracer:
    """The rounds' tracer (adaptive.RoundTracer) of these hits' occlusion rays within
    `dist`, by `opts.engine`."""
    pix = wp.array(hits.pixels, dtype=int, device=bvh.device)
    trace = occlusion_round if opts.engine == "bvh" else occlusion_round_dacrt
    sampler = SAMPLERS[opts.sampler]

    def trace_round(select: np.ndarray, first: int, count: int, mid: int,
                    quarter: int) -> tuple[np.ndarray, ...]:
        return trace(bvh, hits, pix, select, first, count, sampler, opts.seed, dist, nthreads,
                     mid, quarter)

    return trace_round


def occlusion_round(bvh, hits, pix, active, first, count, sampler_id, seed, dist,
                    nthreads, mid, quarter) -> tuple[np.ndarray, ...]:
    """Trace samples first..first+count-1 of the `active` hit pixels: per active pixel, the
    open samples, and those among them with index below `mid` and below `quarter`. The
    rays are split between host threads at pixel boundaries (a CPU launch runs on one
    thread)."""
    device = bvh.device
    m = len(active)
    act = wp.array(active.astype(np.int32), dtype=int, device=device)
    outs = [wp.zeros(m, dtype=int, device=device) for _ in range(3)]
    # More parts than threads, taken in turn (`run_parts`): a round's pixels cost very
    # different amounts (an adaptive round's are clustered where the image is noisy).
    spread = nthreads * PARTS_PER_THREAD if nthreads > 1 else 1
    parts = max(1, min(spread, m * count // PART_RAYS, m), -(-m * count // LAUNCH_RAYS))
    bounds = np.linspace(0, m, parts + 1).astype(int)

    span = int(count) if device.is_cpu else 1
    launch = part_launcher(occlusion_kernel, [
        bvh.arrays, hits.surfaces, pix, act, 0, int(first), int(count), span, sampler_id,
        seed, dist, 1, int(mid), int(quarter), group_rays(parts, isinstance(bvh, Scene), device), 0,
        *outs], device)

    def run(p: int) -> None:
        launch(int(bounds[p + 1] - bounds[p]) * (count // span), {4: int(bounds[p]),
                                                                   15: p * GROUP})

    run_parts(run, parts, nthreads)
    return tuple(out.numpy().astype(np.int64) for out in outs)


def occlusion_round_dacrt(bvh, hits, pix, active, first, count, sampler_id, seed, dist,
                          nthreads, mid, quarter) -> tuple[np.ndarray, ...]:
    """`occlusion_round` with the round's rays traced by DACRT (closest hit within the AO
    distance: occluded if there is one)."""
    m = len(active)
    origins, dirs = _occlusion_rays(hits, first, count, seed, sampler_id, active)
    h = dacrt_trace_mesh(scene_mesh(bvh), origins, dirs, 0.0, dist)
    opened = (h.triangle < 0).reshape(m, count)
    return tuple(opened[:, : max(0, k - first)].sum(axis=1) for k in (first + count, mid,
                                                                        quarter))


def occlusion_rays(hits: PrimaryHits, first: int, count: int, seed: int = 0,
                   sampler: str = "sobol", select: np.ndarray | None = None,
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The origins and unit directions of samples first..first+count-1 of every hit pixel
    (or of the hit pixels `select` indexes), each (H*count, 3) float32, pixel-major:
    exactly the rays `render_ao` traces (for DACRT and for peers in benchmarks/tests)."""
    return _occlusion_rays(hits, first, count, AO_OPTIONS["seed"].check(seed),
                           SAMPLERS[AO_OPTIONS["sampler"].check(sampler)], select)


def _occlusion_rays(hits, first, count, seed, sampler_id, select) -> tuple[np.ndarray, ...]:
    device = hits.surfaces.device
    surfaces, pixels = hits.surfaces, hits.pixels
    if select is not None:
        surfaces, pixels = gather_surfaces(surfaces, select), pixels[select]
    h = len(pixels)
    origins = wp.empty(h * count, dtype=wp.vec3, device=device)
    dirs = wp.empty(h * count, dtype=wp.vec3, device=device)
    if h and count:
        pix = wp.array(pixels, dtype=int, device=device)
        wp.launch(rays_kernel, dim=(h, count),
                  inputs=[surfaces, pix, int(first), int(count), sampler_id, seed],
                  outputs=[origins, dirs], device=device)
    return origins.numpy().reshape(-1, 3), dirs.numpy().reshape(-1, 3)


WARP_MODULES = (occlusion_kernel.module,)  # this module's kernels (core.launch.load_modules)
