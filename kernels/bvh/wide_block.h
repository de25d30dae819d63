    // A leaf block's BLOCK triangles against one ray (wide_simd.h's layout): intersect_triangle
    // (Woop, Benthin, Wald 2013) with the same float32 operations in the same order (no FMA
    // contraction), edge functions that round to zero recomputed in float64 lane by lane as
    // edge_function does. Pasted where WIDE_BLOCK_TEST stands in wide_simd.h and
    // wide_packet.h, after their f4, i4 and splat4.
    auto edge64 = [](float ax, float ay, float bx, float by) {  // edge_function in float64
        const double p = (double)bx * (double)ay;
        const double q = (double)by * (double)ax;
        return (float)(p - q);
    };
    // The lanes of block p whose triangle the ray (origin o*, shear s*, axes k*) meets in
    // [tmin4, bound], with every lane's t, barycentric numerators v, w and 1 / det.
    auto block_test = [&](const float* p, int kx, int ky, int kz, f4 ox, f4 oy, f4 oz, f4 sx,
                          f4 sy, f4 sz, f4 tmin4, float bound, f4& t, f4& v, f4& w,
                          f4& inv_det) -> int {
        const f4 zero = splat4(0.0f), one = splat4(1.0f);
        auto coord4 = [&](int m, int a) {
            f4 c;
            __builtin_memcpy(&c, p + BLOCK * (3 * m + a), sizeof(f4));
            return c;
        };
        const f4 az = coord4(0, kz) - oz, bz = coord4(1, kz) - oz, cz = coord4(2, kz) - oz;
        const f4 sax = sx * az, say = sy * az, sbx = sx * bz, sby = sy * bz;
        const f4 scx = sx * cz, scy = sy * cz;
        const f4 ax = (coord4(0, kx) - ox) - sax, ay = (coord4(0, ky) - oy) - say;
        const f4 bx = (coord4(1, kx) - ox) - sbx, by = (coord4(1, ky) - oy) - sby;
        const f4 cx = (coord4(2, kx) - ox) - scx, cy = (coord4(2, ky) - oy) - scy;
        const f4 u1 = cx * by, u2 = cy * bx, v1 = ax * cy, v2 = ay * cx;
        const f4 w1 = bx * ay, w2 = by * ax;
        f4 u = u1 - u2;
        v = v1 - v2;
        w = w1 - w2;
        const i4 flat = (u == zero) | (v == zero) | (w == zero);
        if (__builtin_ia32_movmskps((f4)flat)) {
            for (int l = 0; l < BLOCK; ++l) {
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
        // Most blocks end here: no triangle's edges enclose the ray (Embree's early out
        // before the division).
        const i4 inside = ~(neg & pos) & (det != zero);
        if (__builtin_ia32_movmskps((f4)inside) == 0)
            return 0;
        const f4 tu = u * (sz * az), tv = v * (sz * bz), tw = w * (sz * cz);
        const f4 t_scaled = (tu + tv) + tw;
        inv_det = one / det;
        t = t_scaled * inv_det;
        const i4 ok = inside & (t >= tmin4) & (t <= splat4(bound));
        return __builtin_ia32_movmskps((f4)ok);
    };
    // Of block p's lanes in `mask` (block_test's), the nearest (`ordered`; else the first)
    // goes into the hit (t, u, v, and its reference `block_index * BLOCK + lane`, from which
    // the finish reads the corners while the block is still cached: bvh/leaf.py) if nearer,
    // or as near at an earlier leaf position (so that ties go alike whatever the order of
    // the visits); true if it did.
    auto lane_at = [&](int ref) {  // block lane `ref`'s first word (wide.lane_word)
        return blocks.data + (long long)(ref / BLOCK) * BLOCK_WORDS + ref % BLOCK;
    };
    auto block_position = [&](int ref) {
        int position;
        __builtin_memcpy(&position, lane_at(ref) + ROW_POSITION * BLOCK, sizeof(int));
        return position;
    };
    auto keep_hit = [&](int block_index, int mask, f4 t, f4 v, f4 w, f4 inv_det, bool ordered,
                        float& hit_t, float& hit_u, float& hit_v, int& hit_ref) -> bool {
        int best = __builtin_ctz(mask);
        if (ordered) {
            for (int m = mask & (mask - 1); m; m &= m - 1) {
                const int l = __builtin_ctz(m);
                if (t[l] < t[best])
                    best = l;
            }
        }
        const int ref = block_index * BLOCK + best;
        if (!(t[best] < hit_t || (t[best] == hit_t && hit_ref >= 0
                                  && block_position(ref) < block_position(hit_ref))))
            return false;
        hit_t = t[best];
        hit_u = v[best] * inv_det[best];
        hit_v = w[best] * inv_det[best];
        hit_ref = ref;
        return true;
    };
