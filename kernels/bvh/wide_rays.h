    // A group of up to RAYS rays in columns, as make_ray makes them (core/ray.py), with each
    // ray's test of a node's boxes and of a leaf's blocks, wide_simd.h's and wide_block.h's
    // operation for operation. Pasted where WIDE_RAYS stands in wide_packet.h and
    // wide_occlusion.h (whose functions take the same arguments), after their RAYS and
    // SAME_SIGNS (see ray_mask); the function returns 0 here where its rays are not for the
    // W = 8 tree or are too many. FMA contraction is off where it is pasted (`#pragma clang
    // fp contract(off)` opens the block).
    static_assert(MAX_WIDTH == 8 && BLOCK == 4, "wide_simd.h's layout");
    typedef float f8 __attribute__((vector_size(8 * sizeof(float))));
    typedef int i8 __attribute__((vector_size(8 * sizeof(int))));
    typedef float f4 __attribute__((vector_size(4 * sizeof(float))));
    typedef int i4 __attribute__((vector_size(4 * sizeof(int))));
    constexpr int width = 8;
    auto splat8 = [](float x) { f8 v = {x, x, x, x, x, x, x, x}; return v; };
    auto splat4 = [](float x) { f4 v = {x, x, x, x}; return v; };
    auto vmin = [](f8 a, f8 b) { return __builtin_ia32_minps256(a, b); };
    auto vmax = [](f8 a, f8 b) { return __builtin_ia32_maxps256(a, b); };
    const float inf = __builtin_inff();
    const int n = last_ray - first_ray;
    if (width_arg != 8 || n <= 0 || n > RAYS)
        return 0;
    const int* words = (const int*)wide.data;
    float org[3][RAYS], inv[3][RAYS], shear[3][RAYS], tlo[RAYS], tfar[RAYS];
    int axis[3][RAYS], near_row[3][RAYS], far_row[3][RAYS];
    float hit_t[RAYS], hit_u[RAYS], hit_v[RAYS];
    int hit_ref[RAYS];
    // Ray k of the arguments into column i, without a hit; false where the SIMD tests do
    // not apply: a direction component 0 (wide_simd.h's careful path), an origin not finite.
    auto load_ray = [&](int i, int k) -> bool {
        const float* o = origins.data[k].c;
        const float* d = directions.data[k].c;
        for (int a = 0; a < 3; ++a) {
            if (!(__builtin_fabsf(o[a]) < inf) || d[a] == 0.0f)
                return false;
            org[a][i] = o[a];
            inv[a][i] = 1.0f / d[a];
            const int s = d[a] < 0.0f;  // the near plane is hi
            near_row[a][i] = (2 * a + s) * width;
            far_row[a][i] = (2 * a + 1 - s) * width;
        }
        const float ad[3] = {__builtin_fabsf(d[0]), __builtin_fabsf(d[1]), __builtin_fabsf(d[2])};
        int kz = 0;
        if (ad[1] > ad[kz])
            kz = 1;
        if (ad[2] > ad[kz])
            kz = 2;
        int kx = (kz + 1) % 3, ky = (kx + 1) % 3;
        if (d[kz] < 0.0f) {
            const int tmp = kx;
            kx = ky;
            ky = tmp;
        }
        axis[0][i] = kx;
        axis[1][i] = ky;
        axis[2][i] = kz;
        shear[0][i] = d[kx] / d[kz];
        shear[1][i] = d[ky] / d[kz];
        shear[2][i] = 1.0f / d[kz];
        tlo[i] = tmin.data[k < tmin.shape[0] ? k : tmin.shape[0] - 1];
        tfar[i] = tmax.data[k < tmax.shape[0] ? k : tmax.shape[0] - 1];
        hit_t[i] = inf;
        hit_u[i] = hit_v[i] = 0.0f;
        hit_ref[i] = -1;
        return true;
    };
    const f8 widen8 = splat8(widen);
    auto row8 = [&](const float* nd, int k) {
        f8 v;
        __builtin_memcpy(&v, nd + k, sizeof(f8));
        return v;
    };
    // Ray i's test of the node's 8 boxes (wide_simd.h's, no zero direction component):
    // the mask of lanes entered, each lane's entry distance in t0. Where every ray's
    // direction has the first one's signs (SAME_SIGNS: a packet), its near and far rows are
    // the first ray's, constant offsets (read per ray, packets ran 7% slower).
    auto ray_mask = [&](const float* nd, int i, f8& t0) -> int {
        const int r = SAME_SIGNS ? 0 : i;
        f8 enter[3], leave[3];
        for (int a = 0; a < 3; ++a) {
            const f8 o = splat8(org[a][i]), v = splat8(inv[a][i]);
            enter[a] = (row8(nd, near_row[a][r]) - o) * v;
            leave[a] = (row8(nd, far_row[a][r]) - o) * v;
        }
        const f8 t_far8 = splat8(tfar[i] < __FLT_MAX__ ? tfar[i] : __FLT_MAX__);
        t0 = vmax(vmax(enter[0], enter[1]), vmax(enter[2], splat8(tlo[i])));
        const i8 in_box = (t0 <= vmin(leave[0] * widen8, leave[1] * widen8))
                          & (t0 <= vmin(leave[2] * widen8, t_far8));
        return __builtin_ia32_movmskps256((f8)in_box);
    };
    // Ray i's test of a leaf's blocks (wide_block.h): the closest hit (`ordered`), or the
    // first one found; true if the ray's hit changed.
WIDE_BLOCK_TEST
    auto leaf_ray = [&](int block, int blocks_used, int i, bool ordered) -> bool {
        const int kx = axis[0][i], ky = axis[1][i], kz = axis[2][i];
        const f4 ox = splat4(org[kx][i]), oy = splat4(org[ky][i]), oz = splat4(org[kz][i]);
        const f4 sx = splat4(shear[0][i]), sy = splat4(shear[1][i]), sz = splat4(shear[2][i]);
        const f4 tmin4 = splat4(tlo[i]);
        bool found = false;
        for (int q = 0; q < blocks_used; ++q) {
            const float* p = blocks.data + (long long)(block + q) * BLOCK_WORDS;
            f4 t, v, w, inv_det;
            const int mask = block_test(p, kx, ky, kz, ox, oy, oz, sx, sy, sz, tmin4,
                                        hit_t[i] < tfar[i] ? hit_t[i] : tfar[i], t, v, w,
                                        inv_det);
            if (mask && keep_hit(block + q, mask, t, v, w, inv_det, ordered, hit_t[i], hit_u[i],
                                 hit_v[i], hit_ref[i])) {
                found = true;
                if (!ordered)
                    break;
            }
        }
        return found;
    };
    // Writes the group's hits to the outputs (t inf, hit reference -1 on a miss: wide_block.h).
    auto store_hits = [&](int n) {
        for (int i = 0; i < n; ++i) {
            const int k = first_ray + i;
            out_t.data[k] = hit_t[i];
            out_u.data[k] = hit_u[i];
            out_v.data[k] = hit_v[i];
            out_triangle.data[k] = hit_ref[i];
        }
    };
