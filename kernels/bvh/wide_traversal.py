"""Closest-hit and any-hit traversal of the wide tree (bvh.wide): all children of a node
tested at once, hit children visited near to far (closest hit) or in lane order (any hit,
which stops at its first hit), as Embree's BVHNNodeTraverser1Hit does
(kernels/bvh/bvh_traverser1.h); a leaf's triangles tested 4 at a time.

A stack entry (and the node being visited) is a reference: 0 none, k + 1 the wide node k,
-(s + 1) the leaf in lane s % 8 of wide node s / 8 (its first block and count are read
from that lane when the leaf is visited; 8 = MAX_WIDTH for every width, so decoding is a
shift).

On a CPU with AVX2 the whole traversal is one native function (`traverse_simd`, clang
vector extensions: Warp compiles CPU kernels for the host's ISA, WARP_FACTS.md), compiled
once per width: a node's W child boxes in one SIMD pass, a leaf block's 4 triangles in
another, the stack a plain uninitialised C array (a Warp vector would be zero-filled, 1 KB
per ray), the nearest hit child kept in a register rather than pushed and popped.
Elsewhere (CUDA, other CPUs) `traverse_wide_portable` makes the same visits lane by lane
with `core.ray.intersect_box` (`wide_node_portable`) and `intersect_triangle`
(`leaf_portable`). Every lane's entry and exit distance is computed with the same float32
operations as `intersect_box` (products and differences in its order, FMA contraction off;
min and max, which are exact, as trees where no NaN can arise), so both make the same
decisions as the binary traversal: the conservative test's guarantee (never miss a box the
exact ray touches) holds lane by lane, and the leaf test is Woop, Benthin and Wald's
watertight test bit for bit, float64 edge fallback included. `wide_node_simd` is
traverse_simd's node visit on its own, for tests.
"""

from __future__ import annotations

import warp as wp

from ..core.box import INF
from ..core.compile_options import MODULE_OPTIONS
from ..core.ray import FAR_WIDEN, Hit, Ray, intersect_box
from ..core.triangle import intersect_triangle
from .leaf import finish_hit
from .node import BvhArrays
from .wide import (
    BLOCK,
    BLOCK_WORDS,
    MAX_WIDTH,
    WIDE_STACK,
    WORDS_PER_LANE,
    WideDists,
    WideStack,
    float_bits,
)

wp.set_module_options(MODULE_OPTIONS)


@wp.func_native(
    """
#if defined(__AVX2__) && !defined(__CUDA_ARCH__)
    return 8;
#else
    return 0;
#endif
"""
)
def simd_lanes() -> int:
    """Lanes of the SIMD box test compiled for this device: 8 on an AVX2 CPU, else 0."""
    ...


# The AVX2 code, in pieces shared by the traversal and the node test that tests compare
# with wide_node_portable (C++ text: a func_native cannot call another).
SIMD_HEADER = """
{
#pragma clang fp contract(off)
    typedef float f8 __attribute__((vector_size(32)));
    typedef int i8 __attribute__((vector_size(32)));
    typedef float f4 __attribute__((vector_size(16)));
    typedef int i4 __attribute__((vector_size(16)));
    auto splat8 = [](float x) { f8 v = {x, x, x, x, x, x, x, x}; return v; };
    auto splat4 = [](float x) { f4 v = {x, x, x, x}; return v; };
    const float inf = __builtin_inff();
    const int* words = (const int*)wide.data;

"""
NODE_SETUP = """
    // Node test, per ray. Slab test of intersect_box, lane-parallel. The near plane of each
    // axis is chosen by the sign of 1/d (+inf where d == 0) instead of min/max of both: the
    // same values. The maxps/minps operand order makes a NaN (0 * inf: an origin on the face
    // of a slab the ray is parallel to) keep the running bound, so that slab does not
    // restrict, as in intersect_box's careful path (faces included).
    int near_row[3], far_row[3];
    f8 org[3], inv[3];
    for (int a = 0; a < 3; ++a) {
        const int s = r.inv_dir.c[a] < 0.0f;  // the near plane is hi
        near_row[a] = (2 * a + s) * width;
        far_row[a] = (2 * a + 1 - s) * width;
        org[a] = splat8(r.origin.c[a]);
        inv[a] = splat8(r.inv_dir.c[a]);
    }
    const f8 tmin8 = splat8(tmin), inf8 = splat8(inf), widen8 = splat8(widen);
    const bool careful = r.any_zero != 0;  // some 1/d is inf: 0 * inf can be NaN
    const i8 lane = {0, 1, 2, 3, 4, 5, 6, 7};
    // Row k of node n (W = 4 fills lanes 4-7 with the unused lane's point at infinity,
    // which no ray enters); constant sizes, so that no copy is a call.
    auto row8 = [&](const float* n, int k) {
        f8 v = inf8;
        if (width == 8)
            __builtin_memcpy(&v, n + k, 32);
        else
            __builtin_memcpy(&v, n + k, 16);
        return v;
    };
    auto words8 = [&](const int* w) {
        i8 v = {0, 0, 0, 0, 0, 0, 0, 0};
        if (width == 8)
            __builtin_memcpy(&v, w, 32);
        else
            __builtin_memcpy(&v, w, 16);
        return v;
    };
"""
NODE_VISIT = """
    // Visit inner node reference `node`: the hit children other than the returned one (0:
    // none hit) go on the stack, nearer ones on top when closest-hit.
    auto visit_node = [&](int node, float t_far) -> int {
        const float* n = wide.data + (long long)(node - 1) * (8 * width);
        f8 enter[3], leave[3];
        for (int a = 0; a < 3; ++a) {
            enter[a] = (row8(n, near_row[a]) - org[a]) * inv[a];
            leave[a] = (row8(n, far_row[a]) - org[a]) * inv[a];
        }
        f8 t0;
        i8 in_box;
        if (careful) {  // a NaN keeps the running bound: a chain in intersect_box's order
            t0 = tmin8;
            f8 t1 = inf8;
            for (int a = 0; a < 3; ++a) {
                t0 = __builtin_ia32_maxps256(enter[a], t0);
                t1 = __builtin_ia32_minps256(leave[a], t1);
            }
            t1 = __builtin_ia32_minps256(t1 * widen8, splat8(t_far));
            in_box = (t0 <= t1) & (t0 < inf8);
        } else {
            // No NaN: min and max are exact, so trees of depth 2 give the same values
            // sooner (the next node's address waits on them); widen * min(f) is
            // min(widen * f), rounding being monotone; t0 <= min(a, b) is t0 <= a and
            // t0 <= b, one level less; and with the far bound made finite, t0 <= it says
            // t0 < inf.
            const f8 t_far8 = splat8(t_far < __FLT_MAX__ ? t_far : __FLT_MAX__);
            t0 = __builtin_ia32_maxps256(__builtin_ia32_maxps256(enter[0], enter[1]),
                                         __builtin_ia32_maxps256(enter[2], tmin8));
            in_box = (t0 <= __builtin_ia32_minps256(leave[0] * widen8, leave[1] * widen8))
                     & (t0 <= __builtin_ia32_minps256(leave[2] * widen8, t_far8));
        }
        const int mask = __builtin_ia32_movmskps256((f8)in_box);
        if (mask == 0)
            return 0;
        // References of the 8 lanes at once: inner child k -> k + 1, leaf -> -(slot + 1).
        const int* w = words + (long long)(node - 1) * (8 * width) + 6 * width;
        const i8 child = words8(w), count = words8(w + width);
        const int slot0 = (node - 1) * 8;
        const i8 slot = (i8){slot0, slot0, slot0, slot0, slot0, slot0, slot0, slot0} + lane;
        const i8 leaf = count > 0;
        const i8 refs = (leaf & ~slot) | (~leaf & (child + 1));
        const int first = __builtin_ctz(mask);
        const int rest = mask & (mask - 1);
        if (rest == 0)
            return refs[first];
        if (!ordered) {  // any hit: lane order (Embree's traverseAnyHit)
#if defined(__AVX512VL__)
            // Packed in registers, then stored whole (WIDE_STACK + 8 entries leave room): a
            // masked store cannot be forwarded to the loads that pop it soon after.
            const unsigned char m8 = (unsigned char)mask;
            const i8 packed_refs = __builtin_ia32_compresssi256_mask(refs, refs, m8);
            const f8 packed_t = __builtin_ia32_compresssf256_mask(t0, t0, m8);
            __builtin_memcpy(stack + sp, &packed_refs, 32);
            __builtin_memcpy(dists + sp, &packed_t, 32);
            sp += __builtin_popcount(mask) - 1;
#else
            for (int m = mask; m; m &= m - 1) {
                stack[sp] = refs[__builtin_ctz(m)];
                dists[sp] = t0[__builtin_ctz(m)];
                ++sp;
            }
            --sp;
#endif
            return refs[31 - __builtin_clz(mask)];  // the top, without a load
        }
        // Closest hit: the hit children in the stack farthest deepest, the nearest taken
        // back (Embree's traverseClosestHit sorts them likewise); at equal distances the
        // later lane is nearer.
        const int second = __builtin_ctz(rest);
        if ((rest & (rest - 1)) == 0) {  // two: the commonest case, without a loop
            const int near = t0[second] <= t0[first] ? second : first;
            const int far = first + second - near;
            stack[sp] = refs[far];
            dists[sp] = t0[far];
            ++sp;
            return refs[near];
        }
        const int top = sp;
        for (int m = mask; m; m &= m - 1) {
            const int j = __builtin_ctz(m);
            const float tj = t0[j];
            int p = sp;
            while (p > top && dists[p - 1] < tj) {
                stack[p] = stack[p - 1];
                dists[p] = dists[p - 1];
                --p;
            }
            stack[p] = refs[j];
            dists[p] = tj;
            ++sp;
        }
        --sp;
        return stack[sp];
    };
"""
LEAF_SETUP = """
    // Leaf test, per ray: intersect_triangle (Woop, Benthin, Wald 2013) on the 4 triangles
    // of a block with the same float32 operations in the same order (no FMA contraction),
    // edge functions that round to zero recomputed in float64 lane by lane as
    // edge_function does.
    auto row4 = [](const float* p, int k) { f4 v; __builtin_memcpy(&v, p + 4 * k, 16); return v; };
    auto edge64 = [](float ax, float ay, float bx, float by) {  // edge_function in float64
        const double p = (double)bx * (double)ay;
        const double q = (double)by * (double)ax;
        return (float)(p - q);
    };
    const int kx = r.kx, ky = r.ky, kz = r.kz;
    const f4 ox = splat4(r.origin.c[kx]), oy = splat4(r.origin.c[ky]), oz = splat4(r.origin.c[kz]);
    const f4 sx = splat4(r.shear.c[0]), sy = splat4(r.shear.c[1]), sz = splat4(r.shear.c[2]);
    const f4 zero = splat4(0.0f), one = splat4(1.0f), tmin4 = splat4(tmin);
"""
TRAVERSE_BODY = (SIMD_HEADER + NODE_SETUP + LEAF_SETUP + """
    // The stack: uninitialised (a Warp vector would be zero-filled, 1 KB per ray).
    int stack[WIDE_STACK + 8];
    float dists[WIDE_STACK + 8];
    int sp = 0;
"""
                 + NODE_VISIT + """
    // Visit the leaf in lane slot % 8 of wide node slot / 8: a closer hit goes into `hit`
    // with its leaf position; true when an any-hit ray is done.
    auto visit_leaf = [&](int slot) -> bool {
        const int* lane_words = words + (long long)(slot >> 3) * (8 * width) + (slot & 7);
        const int block = lane_words[6 * width];
        const int blocks_used = (lane_words[7 * width] + 3) >> 2;
        for (int q = 0; q < blocks_used; ++q) {
            const float* p = blocks.data + (long long)(block + q) * 40;
            const f4 az = row4(p, kz) - oz, bz = row4(p, 3 + kz) - oz, cz = row4(p, 6 + kz) - oz;
            const f4 sax = sx * az, say = sy * az, sbx = sx * bz, sby = sy * bz;
            const f4 scx = sx * cz, scy = sy * cz;
            const f4 ax = (row4(p, kx) - ox) - sax, ay = (row4(p, ky) - oy) - say;
            const f4 bx = (row4(p, 3 + kx) - ox) - sbx, by = (row4(p, 3 + ky) - oy) - sby;
            const f4 cx = (row4(p, 6 + kx) - ox) - scx, cy = (row4(p, 6 + ky) - oy) - scy;
            const f4 u1 = cx * by, u2 = cy * bx, v1 = ax * cy, v2 = ay * cx;
            const f4 w1 = bx * ay, w2 = by * ax;
            f4 u = u1 - u2, v = v1 - v2, w = w1 - w2;
            const i4 flat = (u == zero) | (v == zero) | (w == zero);
            if (__builtin_ia32_movmskps((f4)flat)) {
                for (int l = 0; l < 4; ++l) {
                    if (u[l] == 0.0f)
                        u[l] = edge64(bx[l], by[l], cx[l], cy[l]);
                    if (v[l] == 0.0f)
                        v[l] = edge64(cx[l], cy[l], ax[l], ay[l]);
                    if (w[l] == 0.0f)
                        w[l] = edge64(ax[l], ay[l], bx[l], by[l]);
                }
            }
            const i4 neg = (u < zero) | (v < zero) | (w < zero);
            const i4 pos = (u > zero) | (v > zero) | (w > zero);
            const f4 det = (u + v) + w;
            // Most blocks end here: no triangle's edges enclose the ray (Embree's early
            // out before the division).
            const i4 inside = ~(neg & pos) & (det != zero);
            if (__builtin_ia32_movmskps((f4)inside) == 0)
                continue;
            const f4 tu = u * (sz * az), tv = v * (sz * bz), tw = w * (sz * cz);
            const f4 t_scaled = (tu + tv) + tw;
            const f4 inv_det = one / det;
            const f4 t = t_scaled * inv_det;
            const float bound = hit.t < tmax ? hit.t : tmax;
            const i4 ok = inside & (t >= tmin4) & (t <= splat4(bound));
            const int mask = __builtin_ia32_movmskps((f4)ok);
            if (mask == 0)
                continue;
            int best = __builtin_ctz(mask);
            if (ordered) {
                for (int m = mask & (mask - 1); m; m &= m - 1) {
                    const int l = __builtin_ctz(m);
                    if (t[l] < t[best])
                        best = l;
                }
            }
            if (t[best] < hit.t) {
                hit.t = t[best];
                hit.u = v[best] * inv_det[best];
                hit.v = w[best] * inv_det[best];
                int pos_i;
                __builtin_memcpy(&pos_i, p + 36 + best, 4);
                hit.triangle = pos_i;
                if (!ordered)
                    return true;
            }
        }
        return false;
    };

    // A reference (module docstring): the root first; popped entries that start beyond the
    // closest hit are skipped.
    int node = 1;
    while (true) {
        if (node > 0) {
            node = visit_node(node, hit.t < tmax ? hit.t : tmax);
        } else {
            if (visit_leaf(-node - 1))
                return 1;
            node = 0;
        }
        const float best = hit.t < tmax ? hit.t : tmax;
        while (node == 0 && sp > 0) {
            --sp;
            if (dists[sp] <= best)
                node = stack[sp];
        }
        if (node == 0)
            return 0;
    }
}
""")
# Compiled once per width, so that row offsets are constants and the loads need no
# branch (a block may redeclare the parameter `width`).
TRAVERSE_SIMD = ("#if defined(__AVX2__) && !defined(__CUDA_ARCH__)\n"
                 + "if (width == 8) {\n    constexpr int width = 8;" + TRAVERSE_BODY
                 + "} else {\n    constexpr int width = 4;" + TRAVERSE_BODY + """}
#else
    return 0;
#endif
""").replace("WIDE_STACK", str(WIDE_STACK))
WIDE_NODE_SIMD = ("#if defined(__AVX2__) && !defined(__CUDA_ARCH__)" + SIMD_HEADER + NODE_SETUP
                  + """
    int* stack = stack_vec.c;
    float* dists = dists_vec.c;
""" + NODE_VISIT + """
    return visit_node(node, tmax);
}
#else
    return 0;
#endif
""")


@wp.func_native(TRAVERSE_SIMD)
def traverse_simd(wide: wp.array(dtype=float), blocks: wp.array(dtype=float), width: int,
                  r: Ray, tmin: float, tmax: float, ordered: int, widen: float,
                  hit: wp.ref[Hit]) -> int:
    """traverse_wide_portable on an AVX2 CPU, in one native function: the closest hit (or
    with `ordered` 0 the first hit found) goes into `hit` (t = inf, triangle -1 on entry)
    with its leaf position; returns 1 when an any-hit ray found one."""
    ...


@wp.func_native(WIDE_NODE_SIMD)
def wide_node_simd(wide: wp.array(dtype=float), width: int, node: int, r: Ray, tmin: float,
                   tmax: float, ordered: int, widen: float, stack_vec: wp.ref[WideStack],
                   dists_vec: wp.ref[WideDists], sp: wp.ref[int]) -> int:
    """traverse_simd's visit of inner node reference `node` (for tests, against
    wide_node_portable): the hit children other than the returned one (0: none hit) go on
    the stack, which needs 8 entries free above `sp`."""
    ...


@wp.func
def lane_ref(wide: wp.array(dtype=float), base: int, width: int, node: int, j: int) -> int:
    """The reference of child lane j of wide node reference `node` (at word `base`)."""
    if float_bits(wide[base + 7 * width + j]) > 0:
        return -((node - 1) * MAX_WIDTH + j + 1)
    return float_bits(wide[base + 6 * width + j]) + 1


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
    """leaf_simd triangle by triangle with intersect_triangle."""
    for k in range(count):
        base = (block + k / BLOCK) * BLOCK_WORDS + k % BLOCK
        v0 = wp.vec3(bvh.blocks[base], bvh.blocks[base + BLOCK], bvh.blocks[base + 2 * BLOCK])
        v1 = wp.vec3(bvh.blocks[base + 3 * BLOCK], bvh.blocks[base + 4 * BLOCK],
                     bvh.blocks[base + 5 * BLOCK])
        v2 = wp.vec3(bvh.blocks[base + 6 * BLOCK], bvh.blocks[base + 7 * BLOCK],
                     bvh.blocks[base + 8 * BLOCK])
        h = intersect_triangle(r, v0, v1, v2, tmin, wp.min(hit.t, tmax))
        if h[0] < hit.t:
            hit.t = h[0]
            hit.u = h[1]
            hit.v = h[2]
            hit.triangle = float_bits(bvh.blocks[base + 9 * BLOCK])
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
            base = (slot >> 3) * WORDS_PER_LANE * bvh.width + (slot & 7)
            block = float_bits(bvh.wide[base + 6 * bvh.width])
            count = float_bits(bvh.wide[base + 7 * bvh.width])
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
    """`traversal.traverse` on the wide tree. The root's own box is not tested: its
    children's are."""
    hit = Hit()
    hit.t = INF
    hit.triangle = -1
    done = bool(False)
    if simd_lanes() > 0:
        done = traverse_simd(bvh.wide, bvh.blocks, bvh.width, r, tmin, tmax,
                             wp.where(any_hit, 0, 1), FAR_WIDEN, hit) != 0
    else:
        done = traverse_wide_portable(bvh, r, tmin, tmax, any_hit, hit)
    if done:
        hit.triangle = bvh.tri_ids[hit.triangle]
        return hit
    return finish_hit(bvh, r, tmin, tmax, hit)
