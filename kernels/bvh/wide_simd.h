// The wide BVH's traversal on a CPU with AVX2: bvh/wide_traversal.py's traverse_simd, and
// its node visit alone (wide_node_simd, for tests against wide_node_portable).
//
// How this text is compiled: it is the body of those two `wp.func_native` functions, read
// and wrapped by wide_traversal.py (`simd_function`), which
//   - compiles it only where AVX2 is, on a CPU (SIMD_GUARD: `__AVX2__` and not CUDA); the
//     function returns 0 elsewhere and the portable traversal runs instead;
//   - declares first, as `constexpr int`, the layout constants of bvh/wide.py
//     (NATIVE_LAYOUT): ROW_CHILD, ROW_COUNT, WORDS_PER_LANE, MAX_WIDTH, BLOCK, ROW_POSITION,
//     BLOCK_WORDS, WIDE_STACK. No number of the layout is written here;
//   - pastes it twice, once with `constexpr int width = 8` in scope and once with 4, so that
//     row offsets are constants and the loads need no branch;
//   - defines WIDE_SIMD_NODE_TEST for wide_node_simd, whose parameters differ: the node
//     visit on the caller's stack (`stack_vec`, `dists_vec`, `sp`), returning its result.
// No headers (Warp's clang ships none): clang vector extensions and __builtin_ia32_*.
//
// Instruction sets, two branches:
//   AVX2       required: a node's W child boxes in one pass of 8-float vectors (256 bits,
//              MAX_WIDTH lanes: W = 4 fills lanes 4-7 with the point at infinity), a leaf
//              block's BLOCK triangles in one pass of 4-float vectors (128 bits); vmaxps /
//              vminps in an operand order that keeps a NaN out, vmovmskps for the masks.
//   AVX-512VL  where the CPU has it too (x86-64-v4: Skylake-X, Zen 4 and later): an
//              any-hit ray packs its hit children with vpcompressd / vcompressps in
//              registers and stores them whole; without it, a loop over the mask's bits.
//              Both push the same entries in the same order (tests build each branch with
//              clang's -target-cpu and compare). A 16-lane AVX-512 node test would need
//              nodes of W = 16 (Embree stops at 8 too): not built.
//
// Memory (bvh/wide.py, the byte offsets for W = 8), 32-bit words:
//   wide node k: WORDS_PER_LANE rows of W words from word WORDS_PER_LANE * W * k
//     bytes [  0,  32) lo_x   float32 per child lane   (row 2a: lo on axis a)
//           [ 32,  64) hi_x                            (row 2a + 1: hi on axis a)
//           [ 64,  96) lo_y    [ 96, 128) hi_y    [128, 160) lo_z    [160, 192) hi_z
//           [192, 224) child  int32 (row ROW_CHILD): inner child: its node index;
//                             leaf: its first block
//           [224, 256) count  int32 (row ROW_COUNT): 0 inner child, > 0 leaf triangles
//   leaf block b: BLOCK_WORDS words (160 bytes) from word BLOCK_WORDS * b, rows of BLOCK:
//     bytes [  0,  48) v0.x v0.y v0.z   (row 3m + a: coordinate a of vertex m)
//           [ 48,  96) v1.x v1.y v1.z
//           [ 96, 144) v2.x v2.y v2.z
//           [144, 160) int32 leaf-order position of each triangle (row ROW_POSITION)
// A stack entry is a reference: k + 1 the wide node k, -(s + 1) the leaf in lane
// s % MAX_WIDTH of wide node s / MAX_WIDTH.
//
// Every float32 operation is intersect_box's and intersect_triangle's, in their order,
// FMA contraction off, so that every decision and distance is bit-identical to the
// portable traversal's (docs/architecture.md, "Wide BVH").
{
#pragma clang fp contract(off)
    static_assert(MAX_WIDTH == 8, "a node's lanes fill one 256-bit AVX register");
    static_assert(BLOCK == 4, "a block's triangles fill one 128-bit register");
    static_assert(width <= MAX_WIDTH, "");
    typedef float f8 __attribute__((vector_size(MAX_WIDTH * sizeof(float))));
    typedef int i8 __attribute__((vector_size(MAX_WIDTH * sizeof(int))));
    typedef float f4 __attribute__((vector_size(BLOCK * sizeof(float))));
    typedef int i4 __attribute__((vector_size(BLOCK * sizeof(int))));
    // a reference's lane and node (shifts: the references of leaves are not negative)
    constexpr int LANE_BITS = __builtin_ctz(MAX_WIDTH), BLOCK_BITS = __builtin_ctz(BLOCK);
    static_assert(1 << LANE_BITS == MAX_WIDTH && 1 << BLOCK_BITS == BLOCK, "");
    auto splat8 = [](float x) { f8 v = {x, x, x, x, x, x, x, x}; return v; };
    auto splat4 = [](float x) { f4 v = {x, x, x, x}; return v; };
    const float inf = __builtin_inff();
    const int* words = (const int*)wide.data;

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
    // Row k of node n: W words, lanes past W keep the unused lane's point at infinity,
    // which no ray enters; a constant size, so that no copy is a call.
    auto row8 = [&](const float* n, int k) {
        f8 v = inf8;
        __builtin_memcpy(&v, n + k, width * sizeof(float));
        return v;
    };
    auto words8 = [&](const int* w) {
        i8 v = {0, 0, 0, 0, 0, 0, 0, 0};
        __builtin_memcpy(&v, w, width * sizeof(int));
        return v;
    };

#if defined(WIDE_SIMD_NODE_TEST)
    int* stack = stack_vec.c;
    float* dists = dists_vec.c;
#else
    // Leaf test, per ray: block_test and keep_hit (wide_block.h).
WIDE_BLOCK_TEST
    const int kx = r.kx, ky = r.ky, kz = r.kz;
    const f4 ox = splat4(r.origin.c[kx]), oy = splat4(r.origin.c[ky]), oz = splat4(r.origin.c[kz]);
    const f4 sx = splat4(r.shear.c[0]), sy = splat4(r.shear.c[1]), sz = splat4(r.shear.c[2]);
    const f4 tmin4 = splat4(tmin);

    // The stack: uninitialised (a Warp vector would be zero-filled, 1 KB per ray), with
    // MAX_WIDTH entries to spare for a whole-vector store.
    int stack[WIDE_STACK + MAX_WIDTH];
    float dists[WIDE_STACK + MAX_WIDTH];
    int sp = 0;
#endif

    // Visit inner node reference `node`: the hit children other than the returned one (0:
    // none hit) go on the stack, nearer ones on top when closest-hit.
    auto visit_node = [&](int node, float t_far) -> int {
        const float* n = wide.data + (long long)(node - 1) * (WORDS_PER_LANE * width);
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
        const int* w = words + (long long)(node - 1) * (WORDS_PER_LANE * width);
        const i8 child = words8(w + ROW_CHILD * width), count = words8(w + ROW_COUNT * width);
        const int slot0 = (node - 1) * MAX_WIDTH;
        const i8 slot = (i8){slot0, slot0, slot0, slot0, slot0, slot0, slot0, slot0} + lane;
        const i8 leaf = count > 0;
        const i8 refs = (leaf & ~slot) | (~leaf & (child + 1));
        const int first = __builtin_ctz(mask);
        const int rest = mask & (mask - 1);
        if (rest == 0)
            return refs[first];
        if (!ordered) {  // any hit: lane order (Embree's traverseAnyHit)
#if defined(__AVX512VL__)
            // Packed in registers, then stored whole (MAX_WIDTH entries to spare): a masked
            // store cannot be forwarded to the loads that pop it soon after.
            const unsigned char m8 = (unsigned char)mask;
            const i8 packed_refs = __builtin_ia32_compresssi256_mask(refs, refs, m8);
            const f8 packed_t = __builtin_ia32_compresssf256_mask(t0, t0, m8);
            __builtin_memcpy(stack + sp, &packed_refs, sizeof(i8));
            __builtin_memcpy(dists + sp, &packed_t, sizeof(f8));
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

#if defined(WIDE_SIMD_NODE_TEST)
    return visit_node(node, tmax);
#else
    // Visit the leaf of reference -(slot + 1): a closer hit goes into `hit` with its block
    // lane (keep_hit); true when an any-hit ray is done.
    auto visit_leaf = [&](int slot) -> bool {
        const int* lane_words = words + (long long)(slot >> LANE_BITS) * (WORDS_PER_LANE * width)
                                + (slot & (MAX_WIDTH - 1));
        const int block = lane_words[ROW_CHILD * width];
        const int blocks_used = (lane_words[ROW_COUNT * width] + BLOCK - 1) >> BLOCK_BITS;
        for (int q = 0; q < blocks_used; ++q) {
            const float* p = blocks.data + (long long)(block + q) * BLOCK_WORDS;
            f4 t, v, w, inv_det;
            const int mask = block_test(p, kx, ky, kz, ox, oy, oz, sx, sy, sz, tmin4,
                                        hit.t < tmax ? hit.t : tmax, t, v, w, inv_det);
            if (mask && keep_hit(block + q, mask, t, v, w, inv_det, ordered, hit.t, hit.u, hit.v,
                                 hit.triangle) && !ordered)
                return true;
        }
        return false;
    };

    // A reference (above): the root first; popped entries that start beyond the closest
    // hit are skipped.
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
#endif
}
