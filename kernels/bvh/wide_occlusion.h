// Any-hit traversal of a group of up to GROUP (64) rays through the wide tree (W = 8) on a
// CPU with AVX2: bvh/packet.py's traverse_occlusion_simd. A masked packet (Wald,
// Slusallek, Benthin, Wagner 2001, "Interactive rendering with coherent ray tracing"):
// each stack entry carries the bit mask of the group's rays that entered its box, and each
// of those rays tests the node's 8 boxes as wide_simd.h does; their masks of 8 lanes,
// a byte per ray, are transposed into a mask of rays per lane. Rays from one point or from
// nearby points (the AO rays of neighbouring camera hits, a bake's texels) share the
// descent to the leaves around their origins, about half of an occlusion ray's node
// visits (a zero-length AO ray visits 6.25 of a full one's 8.2 nodes on the dragon), and
// the group walks those nodes once; the stack, the branches and the node's words are
// shared by all its rays.
//
// Compiled as wide_simd.h is (its header): the body of a `wp.func_native`, AVX2 only,
// NATIVE_LAYOUT's constants declared first; the byte layout it reads is wide_simd.h's.
//
// Exactness: a ray's box and triangle tests are wide_simd.h's, operation for operation
// (wide_rays.h, FMA contraction off), and a ray visits exactly the nodes and leaves its
// own any-hit traversal visits, in the same order (children pushed in lane order, the
// highest lane on top), up to its first hit: it reports the same triangle, t, u and v.
// Returns 0 (the caller traces the rays one by one) where this does not apply: W != 8,
// more than GROUP rays, a direction with a zero component (wide_simd.h's careful path),
// an origin that is not finite.
{
    auto group = [&]() __attribute__((noinline)) -> int {
#pragma clang fp contract(off)
    static_assert(GROUP <= 64, "a ray's bit in a 64-bit mask");
    constexpr int RAYS = GROUP;
    constexpr bool SAME_SIGNS = false;
WIDE_RAYS
    for (int i = 0; i < n; ++i)
        if (!load_ray(i, first_ray + i))
            return 0;

    // The stack: a reference (wide_simd.h's) and the rays that entered its box.
    int stack_ref[WIDE_STACK + MAX_WIDTH];
    unsigned long long stack_rays[WIDE_STACK + MAX_WIDTH];
    int sp = 0;
    unsigned long long open = n == 64 ? ~0ull : (1ull << n) - 1;  // the rays without a hit
    stack_ref[sp] = 1;
    stack_rays[sp++] = open;
    const i8 lane = {0, 1, 2, 3, 4, 5, 6, 7};
    while (sp > 0) {
        --sp;
        const int ref = stack_ref[sp];
        const unsigned long long rays = stack_rays[sp] & open;
        if (rays == 0)
            continue;
        if (ref < 0) {  // a leaf: its rays test it
            const int slot = -ref - 1;
            const int* lw = words + (long long)(slot >> 3) * (WORDS_PER_LANE * width)
                            + (slot & (MAX_WIDTH - 1));
            const int block = lw[ROW_CHILD * width];
            const int used = (lw[ROW_COUNT * width] + BLOCK - 1) / BLOCK;
            for (unsigned long long m = rays; m; m &= m - 1) {
                const int i = __builtin_ctzll(m);
                if (leaf_ray(block, used, i, false))
                    open &= ~(1ull << i);
            }
            if (open == 0)
                break;
            continue;
        }
        // Each ray's 8 lanes, one byte per ray in words of 8 rays, each word transposed
        // into a byte of rays per lane (the 8 x 8 bit matrix transpose of Hacker's
        // Delight, 7-3).
        const float* nd = wide.data + (long long)(ref - 1) * (WORDS_PER_LANE * width);
        constexpr int WORDS = (GROUP + 7) / 8;
        unsigned long long x[WORDS] = {};
        unsigned entered = 0;
        f8 t0;
        for (unsigned long long m = rays; m; m &= m - 1) {
            const int i = __builtin_ctzll(m);
            const unsigned lanes = (unsigned)ray_mask(nd, i, t0);
            entered |= lanes;
            x[i >> 3] |= (unsigned long long)lanes << (8 * (i & 7));
        }
        if (entered == 0)
            continue;
        for (int q = 0; q < WORDS; ++q) {
            unsigned long long y = x[q];
            unsigned long long t = (y ^ (y >> 7)) & 0x00AA00AA00AA00AAull;
            y = y ^ t ^ (t << 7);
            t = (y ^ (y >> 14)) & 0x0000CCCC0000CCCCull;
            y = y ^ t ^ (t << 14);
            t = (y ^ (y >> 28)) & 0x00000000F0F0F0F0ull;
            x[q] = y ^ t ^ (t << 28);
        }
        // References of the 8 lanes (wide_simd.h's), pushed in lane order: the highest lane
        // is visited first, as a single any-hit ray visits it.
        const int* w = words + (long long)(ref - 1) * (WORDS_PER_LANE * width);
        i8 child, count;
        __builtin_memcpy(&child, w + ROW_CHILD * width, sizeof(i8));
        __builtin_memcpy(&count, w + ROW_COUNT * width, sizeof(i8));
        const int slot0 = (ref - 1) * MAX_WIDTH;
        const i8 slot = (i8){slot0, slot0, slot0, slot0, slot0, slot0, slot0, slot0} + lane;
        const i8 leaf = count > 0;
        const i8 refs = (leaf & ~slot) | (~leaf & (child + 1));
        for (unsigned m = entered; m; m &= m - 1) {
            const int j = __builtin_ctz(m);
            stack_ref[sp] = refs[j];
            unsigned long long rays_j = 0;
            for (int q = 0; q < WORDS; ++q)
                rays_j |= ((x[q] >> (8 * j)) & 0xffull) << (8 * q);
            stack_rays[sp++] = rays_j;
        }
    }
    store_hits(n);
    return 1;
    };
    return group();
}
