// Closest-hit traversal of a packet of coherent rays through the wide tree (W = 8) on a CPU
// with AVX2: bvh/packet.py's traverse_packet_simd. Ranged packet traversal (Overbeck,
// Ramamoorthi, Mark 2008, "Large ray packets for real-time Whitted ray tracing"; the
// packet traversal of tinybvh follows it): a node is entered with the range [first, last]
// of the packet's rays that may reach it; each child gets the first and the last ray of
// that range whose own box test passes, found by scanning from each end, and a conservative
// interval test of the whole packet (the frustum) skips children no ray can enter without
// a scan. Coherent rays (a camera's rays over a small tile) keep whole ranges: a node then
// costs a frustum test and two ray tests instead of one test per ray.
// Where a range is down to SINGLE_RANGE rays or fewer, each of them goes on alone through
// the subtree (subtree_ray: the single-ray traversal from that node), as Embree's hybrid
// traversal drops to single rays when few are active: fine meshes' camera rays part at
// the leaves, where the range's frustum and scans cost more than they save.
//
// Compiled as wide_simd.h is (its header): the body of a `wp.func_native`, AVX2 only,
// NATIVE_LAYOUT's constants declared first; the byte layout it reads is wide_simd.h's.
//
// Exactness: a ray's box and triangle tests are wide_simd.h's, operation for operation
// (FMA contraction off). A ray in a range whose own test of an ancestor was skipped may
// test a leaf the single-ray traversal never reaches; the triangle test decides a hit
// alone, and that traversal misses no box holding a hit (the conservative slab test), so
// the closest hit is the same (at equal t the first leaf position, in every traversal),
// but for overlapping coplanar triangles that meet a ray at one refined distance with
// float32 t's that differ (which one wins follows the order, as between tree widths).
// Children are visited in the order of the first ray of their range, as that ray alone
// would visit them: the float32 t of a hit can be off by more than the gap to a box
// behind it (Conference: 1.4e-2 at t = 1266, 90 ulps), which a box pruned by that t then
// hides, so an order of the packet's own (by the frustum's bound) gave another surface
// 0.009 farther on 1 ray in 4.9M.
// Returns 0 (the caller traces the packet ray by ray) where this does not apply: W != 8,
// more than PACKET rays, a direction with a zero component or a sign differing from the
// first ray's on some axis (no single near plane per axis), a non-finite origin.
{
    // Out of line: called once a packet, and inlined it made the film kernel around it
    // slower even where it never ran.
    auto packet = [&]() __attribute__((noinline)) -> int {
#pragma clang fp contract(off)
    constexpr int RAYS = PACKET;
    // Time of packets over ray by ray, 512² camera rays, one thread, one process: without
    // subtree_ray -> with it: blade 0.95 -> 0.82, buddha 0.94 -> 0.89, conference 0.63 ->
    // 0.64; at 256², buddha 1.10 -> 0.91 (1, 2, 4 and 16 were slower)
    constexpr int SINGLE_RANGE = 8;
    constexpr bool SAME_SIGNS = true;
WIDE_RAYS
    int negative[3];
    for (int i = 0; i < n; ++i) {
        if (!load_ray(i, first_ray + i))
            return 0;
        for (int a = 0; a < 3; ++a) {
            const int s = inv[a][i] < 0.0f;
            if (i == 0)
                negative[a] = s;
            else if (s != negative[a])
                return 0;
        }
    }
    // The packet's bounds, for the frustum test: origins, inverse directions (one sign per
    // axis), the lowest tmin and the highest far bound (kept up to date as hits come).
    float omin[3], omax[3], imin[3], imax[3];
    float tlo_min = inf, tfar_max = -inf;
    for (int a = 0; a < 3; ++a) {
        omin[a] = omax[a] = org[a][0];
        imin[a] = imax[a] = inv[a][0];
        for (int i = 1; i < n; ++i) {
            omin[a] = org[a][i] < omin[a] ? org[a][i] : omin[a];
            omax[a] = org[a][i] > omax[a] ? org[a][i] : omax[a];
            imin[a] = inv[a][i] < imin[a] ? inv[a][i] : imin[a];
            imax[a] = inv[a][i] > imax[a] ? inv[a][i] : imax[a];
        }
    }
    for (int i = 0; i < n; ++i) {
        tlo_min = tlo[i] < tlo_min ? tlo[i] : tlo_min;
        tfar_max = tfar[i] > tfar_max ? tfar[i] : tfar_max;
    }
    // Coherence: rays from points farther apart than a 64th of the scene, or whose unit
    // directions spread over more than COHERENT_SPREAD on an axis, went 1.4-1.9x slower
    // as a packet than one by one (scattered origins, directions over an octant).
    {
        const float* root = wide.data;
        float dmin[3], dmax[3];
        for (int a = 0; a < 3; ++a) {
            float lo = inf, hi = -inf;
            for (int j = 0; j < width; ++j) {
                const float l = root[2 * a * width + j], h = root[(2 * a + 1) * width + j];
                if (l <= h) {
                    lo = l < lo ? l : lo;
                    hi = h > hi ? h : hi;
                }
            }
            if (omax[a] - omin[a] > (hi - lo) * (1.0f / 64.0f))
                return 0;
            dmin[a] = inf;
            dmax[a] = -inf;
        }
        for (int i = 0; i < n; ++i) {
            const float* d = directions.data[first_ray + i].c;
            const float s = 1.0f / __builtin_sqrtf(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
            for (int a = 0; a < 3; ++a) {
                dmin[a] = d[a] * s < dmin[a] ? d[a] * s : dmin[a];
                dmax[a] = d[a] * s > dmax[a] ? d[a] * s : dmax[a];
            }
        }
        for (int a = 0; a < 3; ++a)
            if (dmax[a] - dmin[a] > COHERENT_SPREAD)
                return 0;
    }
    // The closest hits finished as leaf.finish_hit finishes them: refine_hit's float64
    // operations in its order, four hits a vector (its five divisions four at a time: the
    // blade's hit rays 312 -> 250 ns against the Warp finish), the corners read from the
    // hit's block lane, the triangle mapped through tri_ids. The same bits as finish_hit.
    auto finish_hits = [&](int n) {
        typedef double d4 __attribute__((vector_size(4 * sizeof(double))));
        double in[15][RAYS + 3];  // per hit: the permuted origin, direction and corners
        int hits[RAYS];
        int count = 0;
        for (int i = 0; i < n; ++i) {
            const int k = first_ray + i;
            out_t.data[k] = hit_t[i];
            out_u.data[k] = hit_u[i];
            out_v.data[k] = hit_v[i];
            out_triangle.data[k] = -1;
            if (hit_ref[i] < 0)
                continue;
            const float* d = directions.data[k].c;
            const float* c = lane_at(hit_ref[i]);
            for (int a = 0; a < 3; ++a) {
                const int ka = axis[a][i];
                in[a][count] = (double)org[ka][i];
                in[3 + a][count] = (double)d[ka];
                for (int m = 0; m < 3; ++m)
                    in[6 + 3 * m + a][count] = (double)c[(3 * m + ka) * BLOCK];
            }
            hits[count++] = i;
        }
        for (int j = count; j < ((count + 3) & ~3); ++j)  // the last vector's spare lanes
            for (int q = 0; q < 15; ++q)
                in[q][j] = in[q][count - 1];
        for (int j = 0; j < count; j += 4) {
            d4 x[15];
            for (int q = 0; q < 15; ++q)
                __builtin_memcpy(&x[q], &in[q][j], sizeof(d4));
            const d4 ox = x[0], oy = x[1], oz = x[2], dz = x[5];
            const d4 sx = x[3] / dz, sy = x[4] / dz;
            const d4 az = x[8] - oz, bz = x[11] - oz, cz = x[14] - oz;
            const d4 ax = (x[6] - ox) - sx * az, ay = (x[7] - oy) - sy * az;
            const d4 bx = (x[9] - ox) - sx * bz, by = (x[10] - oy) - sy * bz;
            const d4 cx = (x[12] - ox) - sx * cz, cy = (x[13] - oy) - sy * cz;
            const d4 u = cx * by - cy * bx, v = ax * cy - ay * cx, w = bx * ay - by * ax;
            const d4 det = (u + v) + w;
            const d4 t = ((u * az + v * bz) + w * cz) / (det * dz);
            const d4 fu = v / det, fv = w / det;
            for (int l = 0; l < 4 && j + l < count; ++l) {
                const int i = hits[j + l], k = first_ray + i;
                out_triangle.data[k] = tri_ids.data[block_position(hit_ref[i])];
                if (det[l] == 0.0)  // refine_hit keeps the float32 hit
                    continue;
                const float lo = tlo[i], hi = tmax.data[k < tmax.shape[0] ? k : tmax.shape[0] - 1];
                out_t.data[k] = __builtin_fminf(__builtin_fmaxf(lo, (float)t[l]), hi);
                out_u.data[k] = (float)fu[l];
                out_v.data[k] = (float)fv[l];
            }
        }
    };
    // The frustum: per box, a lower bound of every ray's entry and an upper bound of every
    // ray's exit, from the same operations at the corners of the packet's bounds (rounding
    // is monotone and (p - o) * v is bilinear, so the corners bound every ray's value).
    auto frustum_mask = [&](const float* nd, f8& lower) -> int {
        f8 lo = splat8(tlo_min), hi = splat8(tfar_max < __FLT_MAX__ ? tfar_max : __FLT_MAX__);
        for (int a = 0; a < 3; ++a) {
            const f8 v0 = splat8(imin[a]), v1 = splat8(imax[a]);
            const f8 np = row8(nd, near_row[a][0]), fp = row8(nd, far_row[a][0]);
            const f8 n0 = np - splat8(omax[a]), n1 = np - splat8(omin[a]);
            const f8 f0 = fp - splat8(omax[a]), f1 = fp - splat8(omin[a]);
            lo = vmax(lo, vmin(vmin(n0 * v0, n0 * v1), vmin(n1 * v0, n1 * v1)));
            hi = vmin(hi, vmax(vmax(f0 * v0, f0 * v1), vmax(f1 * v0, f1 * v1)) * widen8);
        }
        lower = lo;
        return __builtin_ia32_movmskps256((f8)(lo <= hi));
    };

    // The reference of lane j of inner node reference `node` (wide_simd.h's).
    auto child_ref = [&](int node, int j) {
        const int* w = words + (long long)(node - 1) * (WORDS_PER_LANE * width);
        return w[ROW_COUNT * width + j] > 0 ? -((node - 1) * MAX_WIDTH + j + 1)
                                            : w[ROW_CHILD * width + j] + 1;
    };
    // `entry` pushed at distance `dist` among the entries above `top`, farthest deepest, at
    // equal distances the later one nearer (wide_simd.h's order).
    auto push_sorted = [](auto* entries, float* dists, int& sp, int top, auto entry,
                          float dist) {
        int p = sp;
        while (p > top && dists[p - 1] < dist) {
            entries[p] = entries[p - 1];
            dists[p] = dists[p - 1];
            --p;
        }
        entries[p] = entry;
        dists[p] = dist;
        ++sp;
    };
    // Ray i alone through the subtree of reference `root` (wide_simd.h's traversal from
    // there: children near to far by its own entry distances, entries beyond its closest
    // hit skipped); true if its hit changed. Where a packet's range is down to a few rays
    // (SINGLE_RANGE), the range's bookkeeping (frustum, scans from both ends) costs more
    // than it saves: fine meshes' rays part at the leaves.
    auto subtree_ray = [&](int i, int root) -> bool {
        int rstack[WIDE_STACK + MAX_WIDTH];
        float rdist[WIDE_STACK + MAX_WIDTH];
        int rsp = 0, node = root;
        bool found = false;
        f8 t0;
        if (node < 0) {  // a leaf the range's test let in: the ray's own test of its box
            const int slot = -node - 1;
            const float* nd = wide.data + (long long)(slot >> 3) * (WORDS_PER_LANE * width);
            if (!((ray_mask(nd, i, t0) >> (slot & (MAX_WIDTH - 1))) & 1))
                return false;
        }
        while (true) {
            if (node < 0) {
                const int slot = -node - 1;
                const int* lw = words + (long long)(slot >> 3) * (WORDS_PER_LANE * width)
                                + (slot & (MAX_WIDTH - 1));
                if (leaf_ray(lw[ROW_CHILD * width], (lw[ROW_COUNT * width] + BLOCK - 1) / BLOCK,
                             i, true)) {
                    tfar[i] = hit_t[i];
                    found = true;
                }
                node = 0;
            } else {
                const float* nd = wide.data + (long long)(node - 1) * (WORDS_PER_LANE * width);
                const int top = rsp;
                for (int m = ray_mask(nd, i, t0); m; m &= m - 1) {
                    const int j = __builtin_ctz(m);
                    push_sorted(rstack, rdist, rsp, top, child_ref(node, j), t0[j]);
                }
                node = 0;
            }
            while (node == 0 && rsp > 0) {
                --rsp;
                if (rdist[rsp] <= tfar[i])
                    node = rstack[rsp];
            }
            if (node == 0)
                return found;
        }
    };

    // The stack: a reference (wide_simd.h's), its rays' range and the frustum's entry bound.
    struct Entry { int ref, first, last; float lower; };
    Entry stack[WIDE_STACK + MAX_WIDTH];
    float stack_order[WIDE_STACK + MAX_WIDTH];
    int sp = 0;
    stack[sp++] = Entry{1, 0, n - 1, -inf};
    while (sp > 0) {
        const Entry e = stack[--sp];
        if (e.lower > tfar_max)
            continue;
        int first = e.first, last = e.last;
        while (first <= last && tfar[first] < e.lower)
            ++first;
        while (last >= first && tfar[last] < e.lower)
            --last;
        if (first > last)
            continue;
        if (last - first < SINGLE_RANGE) {
            bool shrunk = false;
            for (int i = first; i <= last; ++i)
                shrunk |= subtree_ray(i, e.ref);
            if (shrunk) {
                tfar_max = -inf;
                for (int i = 0; i < n; ++i)
                    tfar_max = tfar[i] > tfar_max ? tfar[i] : tfar_max;
            }
            continue;
        }
        if (e.ref < 0) {  // a leaf: each ray of the range that enters its box tests it
            const int slot = -e.ref - 1, lane = slot & (MAX_WIDTH - 1);
            const float* nd = wide.data + (long long)(slot >> 3) * (WORDS_PER_LANE * width);
            const int* lw = words + (long long)(slot >> 3) * (WORDS_PER_LANE * width) + lane;
            const int block = lw[ROW_CHILD * width];
            const int used = (lw[ROW_COUNT * width] + BLOCK - 1) / BLOCK;
            bool shrunk = false;
            f8 t0;
            for (int i = first; i <= last; ++i) {
                if (((ray_mask(nd, i, t0) >> lane) & 1) && leaf_ray(block, used, i, true)) {
                    tfar[i] = hit_t[i];
                    shrunk = true;
                }
            }
            if (shrunk) {
                tfar_max = -inf;
                for (int i = 0; i < n; ++i)
                    tfar_max = tfar[i] > tfar_max ? tfar[i] : tfar_max;
            }
            continue;
        }
        const float* nd = wide.data + (long long)(e.ref - 1) * (WORDS_PER_LANE * width);
        f8 lower;
        const int maybe = frustum_mask(nd, lower);
        if (maybe == 0)
            continue;
        // SplitRange: each child's first and last ray whose own test passes, and the first
        // ray's entry distance, which orders the children as that ray's traversal would.
        int firsts[MAX_WIDTH], lasts[MAX_WIDTH];
        float order[MAX_WIDTH];
        int open = maybe;
        f8 t0;
        for (int i = first; open && i <= last; ++i) {
            const int m = ray_mask(nd, i, t0) & open;
            for (int b = m; b; b &= b - 1) {
                firsts[__builtin_ctz(b)] = i;
                order[__builtin_ctz(b)] = t0[__builtin_ctz(b)];
            }
            open &= ~m;
        }
        const int entered = maybe & ~open;
        open = entered;
        for (int i = last; open && i >= first; --i) {
            const int m = ray_mask(nd, i, t0) & open;
            for (int b = m; b; b &= b - 1)
                lasts[__builtin_ctz(b)] = i;
            open &= ~m;
        }
        // Children pushed farthest first, the nearest on top, at equal distances the later
        // lane nearer (wide_simd.h's order); each keeps the frustum's entry bound.
        const int top = sp;
        for (int m = entered; m; m &= m - 1) {
            const int j = __builtin_ctz(m);
            push_sorted(stack, stack_order, sp, top,
                        Entry{child_ref(e.ref, j), firsts[j], lasts[j], lower[j]}, order[j]);
        }
    }
    if (finish)
        finish_hits(n);
    else
        store_hits(n);
    return 1;
    };
    return packet();
}
