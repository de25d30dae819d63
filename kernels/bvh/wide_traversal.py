"""Closest-hit and any-hit traversal of the wide tree (bvh.wide): all children of a node
tested at once, hit children visited near to far (closest hit) or in lane order (any hit,
which stops at its first hit), as Embree's BVHNNodeTraverser1Hit does
(kernels/bvh/bvh_traverser1.h); a leaf's triangles tested 4 at a time.

A stack entry (and the node being visited) is a reference: 0 none, k + 1 the wide node k,
-(s + 1) the leaf in lane s % MAX_WIDTH of wide node s / MAX_WIDTH (its first block and
count are read from that lane when the leaf is visited; MAX_WIDTH for every width).

On a CPU with AVX2 the whole traversal is one native function (`traverse_simd`, clang
vector extensions: Warp compiles CPU kernels for the host's ISA, WARP_FACTS.md), written
in wide_simd.h (its header: how it is compiled, its two instruction-set branches, AVX2 and
AVX-512VL, and the byte layout it reads, whose numbers come from bvh.wide's
NATIVE_LAYOUT), compiled once per width: a node's W child boxes in one SIMD pass, a leaf
block's 4 triangles in another, the stack a plain uninitialised C array (a Warp vector
would be zero-filled, 1 KB per ray), the nearest hit child kept in a register rather than
pushed and popped. Elsewhere (CUDA, CPUs without AVX2) `traverse_wide_portable` makes the
same visits lane by lane with `core.ray.intersect_box` (`wide_node_portable`) and
`intersect_triangle` (`leaf_portable`). Every lane's entry and exit distance is computed
with the same float32 operations as `intersect_box` (products and differences in its
order, FMA contraction off; min and max, which are exact, as trees where no NaN can arise),
so both make the same decisions as the binary traversal: the conservative test's guarantee
(never miss a box the exact ray touches) holds lane by lane, and the leaf test is Woop,
Benthin and Wald's watertight test bit for bit, float64 edge fallback included.
`wide_node_simd` is traverse_simd's node visit on its own, for tests; `simd_support` says
which branch a device's kernels were compiled with (bvh.api's default width follows it).
"""

from __future__ import annotations

import functools
from pathlib import Path

import warp as wp

from ..core.box import INF
from ..core.compile_options import MODULE_OPTIONS
from ..core.ray import FAR_WIDEN, Hit, Ray, intersect_box
from ..core.triangle import intersect_triangle
from .node import BvhArrays
from .wide import (
    BLOCK,
    MAX_WIDTH,
    NATIVE_LAYOUT,
    ROW_CHILD,
    ROW_COUNT,
    WORDS_PER_LANE,
    WideDists,
    WideStack,
    float_bits,
    lane_corners,
    lane_position,
)

wp.set_module_options(MODULE_OPTIONS)

# Where the SIMD traversal is compiled: a CPU with AVX2 (Warp compiles CPU kernels for the
# host's ISA, or the target that cpu_compiler_flags names).
SIMD_GUARD = "#if defined(__AVX2__) && !defined(__CUDA_ARCH__)"


@wp.func_native(
    SIMD_GUARD
    + """
#if defined(__AVX512VL__)
    return 2;
#else
    return 1;
#endif
#else
    return 0;
#endif
"""
)
def simd_isa() -> int:
    """The SIMD traversal's branch compiled for this device (wide_simd.h): 0 none (the
    portable traversal runs), 1 AVX2, 2 AVX2 with AVX-512VL."""
    ...


@wp.func_native(
    SIMD_GUARD
    + """
    return 8;
#else
    return 0;
#endif
"""
)
def simd_lanes() -> int:
    """Lanes of the SIMD box test compiled for this device: 8 on an AVX2 CPU, else 0."""
    ...


def native_source(name: str) -> str:
    """A native text of this folder, wide_rays.h pasted where its line WIDE_RAYS is and
    wide_block.h where WIDE_BLOCK_TEST is."""
    here = Path(__file__).parent
    text = (here / name).read_text().replace("WIDE_RAYS\n", (here / "wide_rays.h").read_text())
    return text.replace("WIDE_BLOCK_TEST\n", (here / "wide_block.h").read_text())


SIMD_SOURCE = native_source("wide_simd.h")


def simd_function(node_test: bool) -> str:
    """The body of a `wp.func_native` running wide_simd.h (its header says how): where
    SIMD_GUARD holds, bvh.wide's NATIVE_LAYOUT as constants, then the file once per width
    (8, 4) with `width` a constant; 0 elsewhere."""
    layout = "".join(f"    constexpr int {name} = {int(value)};\n"
                     for name, value in NATIVE_LAYOUT.items())
    entry, leave = (("#define WIDE_SIMD_NODE_TEST\n", "#undef WIDE_SIMD_NODE_TEST\n")
                    if node_test else ("", ""))
    per_width = (f"    if (width == 8) {{\n        constexpr int width = 8;\n{SIMD_SOURCE}    }}"
                 f" else {{\n        constexpr int width = 4;\n{SIMD_SOURCE}    }}\n")
    return f"{SIMD_GUARD}\n{entry}{layout}{per_width}{leave}#else\n    return 0;\n#endif\n"


@wp.func_native(simd_function(node_test=False))
def traverse_simd(wide: wp.array(dtype=float), blocks: wp.array(dtype=float), width: int,
                  r: Ray, tmin: float, tmax: float, ordered: int, widen: float,
                  hit: wp.ref[Hit]) -> int:
    """traverse_wide_portable on an AVX2 CPU, in one native function: the closest hit (or
    with `ordered` 0 the first hit found) goes into `hit` (t = inf, triangle -1 on entry)
    with its leaf position; returns 1 when an any-hit ray found one."""
    ...


@wp.func_native(simd_function(node_test=True))
def wide_node_simd(wide: wp.array(dtype=float), width: int, node: int, r: Ray, tmin: float,
                   tmax: float, ordered: int, widen: float, stack_vec: wp.ref[WideStack],
                   dists_vec: wp.ref[WideDists], sp: wp.ref[int]) -> int:
    """traverse_simd's visit of inner node reference `node` (for tests, against
    wide_node_portable): the hit children other than the returned one (0: none hit) go on
    the stack, which needs MAX_WIDTH entries free above `sp`."""
    ...


@wp.func
def lane_ref(wide: wp.array(dtype=float), base: int, width: int, node: int, j: int) -> int:
    """The reference of child lane j of wide node reference `node` (at word `base`)."""
    if float_bits(wide[base + ROW_COUNT * width + j]) > 0:
        return -((node - 1) * MAX_WIDTH + j + 1)
    return float_bits(wide[base + ROW_CHILD * width + j]) + 1


@wp.func
def wide_node_portable(bvh: BvhArrays, node: int, r: Ray, tmin: float, tmax: float,
                       ordered: bool, stack: wp.ref[WideStack], dists: wp.ref[WideDists],
                       sp: wp.ref[int]) -> int:
    """wide_node_simd lane by lane with intersect_box."""
    w = bvh.width
    base = (node - 1) * WORDS_PER_LANE * w
    top = int(sp)
    for j in range(w):
        lo = wp.vec3(bvh.wide[base + j], bvh.wide[base + 2 * w + j], bvh.wide[base + 4 * w + j])
        hi = wp.vec3(bvh.wide[base + w + j], bvh.wide[base + 3 * w + j],
                     bvh.wide[base + 5 * w + j])
        t = intersect_box(r, lo, hi, tmin, tmax)
        if t < INF:
            p = int(sp)
            while ordered and p > top:
                if dists[p - 1] >= t:
                    break
                stack[p] = stack[p - 1]
                dists[p] = dists[p - 1]
                p -= 1
            stack[p] = lane_ref(bvh.wide, base, w, node, j)
            dists[p] = t
            sp += 1
    if sp == top:
        return 0
    sp -= 1
    return stack[sp]


@wp.func
def leaf_portable(bvh: BvhArrays, block: int, count: int, r: Ray, tmin: float, tmax: float,
                  any_hit: bool, hit: wp.ref[Hit]) -> bool:
    """leaf_simd triangle by triangle with intersect_triangle (the hit: its block lane)."""
    for k in range(count):
        ref = block * BLOCK + k
        c = lane_corners(bvh.blocks, ref)
        h = intersect_triangle(r, c[0], c[1], c[2], tmin, wp.min(hit.t, tmax))
        if h[0] < hit.t or (h[0] == hit.t and hit.triangle >= 0
                            and lane_position(bvh.blocks, ref)
                            < lane_position(bvh.blocks, hit.triangle)):
            hit.t = h[0]
            hit.u = h[1]
            hit.v = h[2]
            hit.triangle = ref
            if any_hit:
                return True
    return False


@wp.func
def traverse_wide_portable(bvh: BvhArrays, r: Ray, tmin: float, tmax: float, any_hit: bool,
                           hit: wp.ref[Hit]) -> bool:
    """traverse_simd lane by lane (CUDA, CPUs without AVX2)."""
    stack = WideStack()
    dists = WideDists()
    sp = int(0)
    node = int(1)
    while True:
        if node > 0:
            node = wide_node_portable(bvh, node, r, tmin, wp.min(hit.t, tmax), not any_hit,
                                      stack, dists, sp)
        else:
            slot = -node - 1
            base = (slot / MAX_WIDTH) * WORDS_PER_LANE * bvh.width + slot % MAX_WIDTH
            block = float_bits(bvh.wide[base + ROW_CHILD * bvh.width])
            count = float_bits(bvh.wide[base + ROW_COUNT * bvh.width])
            if leaf_portable(bvh, block, count, r, tmin, tmax, any_hit, hit):
                return True
            node = 0
        best = wp.min(hit.t, tmax)
        while node == 0 and sp > 0:
            sp -= 1
            if dists[sp] <= best:
                node = stack[sp]
        if node == 0:
            break
    return False


@wp.func
def traverse_wide(bvh: BvhArrays, r: Ray, tmin: float, tmax: float, any_hit: bool) -> Hit:
    """`traversal.traverse_leaf_order` on the wide tree. The root's own box is not tested:
    its children's are."""
    hit = Hit()
    hit.t = INF
    hit.triangle = -1
    if simd_lanes() > 0:
        traverse_simd(bvh.wide, bvh.blocks, bvh.width, r, tmin, tmax,
                      wp.where(any_hit, 0, 1), FAR_WIDEN, hit)
    else:
        traverse_wide_portable(bvh, r, tmin, tmax, any_hit, hit)
    return hit


@wp.kernel(enable_backward=False)
def report_simd(out: wp.array(dtype=int)):
    """out = (simd_lanes(), simd_isa()) as this module is compiled for the device."""
    out[0] = simd_lanes()
    out[1] = simd_isa()


@functools.cache
def _simd_support(alias: str) -> tuple[int, int]:
    out = wp.zeros(2, dtype=int, device=alias)
    wp.launch(report_simd, dim=1, inputs=[out], device=alias)
    lanes, isa = (int(x) for x in out.numpy())
    return lanes, isa


def simd_support(device) -> tuple[int, int]:
    """(simd_lanes(), simd_isa()) of the wide traversal as compiled for this device, asked
    once per process (a one-thread launch; this module's compile options are the traversal
    kernels'); (0, 0) on CUDA, whose kernels traverse the binary tree."""
    device = wp.get_device(device)
    return _simd_support(device.alias) if device.is_cpu else (0, 0)
