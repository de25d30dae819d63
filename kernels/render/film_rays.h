// A packet's samples first .. first + count - 1 of one pixel, eight at a time in 8-lane
// vectors: each sample's occlusion-direction point (sample_2d_at(sampler, key, i),
// sampling.py) into points, always; for a pinhole PERSP camera, also each sample's camera
// ray as sample_ray makes it (filtered.py; returns 1), else 0 and the rays untouched.
// Every step is the Warp code's, operation for operation (sampling.py, film.py,
// camera_ray; Warp's mat33 * vec3 sums its columns left to right, wp.length sums the
// squares left to right, a vec3 / float divides each component), compiled without
// contraction as the Warp code is (core.compile_options): the same bits, which
// tests/kernels/render/test_film_rays.py checks. One by one in Warp, the camera rays took
// ~32 ns a sample, here ~13.
typedef unsigned int u8v __attribute__((vector_size(32)));
typedef int i8v __attribute__((vector_size(32)));
typedef float f8v __attribute__((vector_size(32)));
const bool pinhole = persp == 1 && !(aperture > 0.0f);
// Not inlined: this much code inlined into film_kernel slowed the kernel's traversal
// (~310 against ~260 ns a sample on issue 33's six Suzannes, one thread), run or not.
auto run = [&]() __attribute__((noinline)) {
    auto pcg = [](u8v x) -> u8v {  // sampling.pcg_hash
        const u8v state = x * 747796405u + 2891336453u;
        const u8v word = ((state >> ((state >> 28u) + 4u)) ^ state) * 277803737u;
        return (word >> 22u) ^ word;
    };
    auto swap_bits = [](u8v x, unsigned mask, unsigned shift) -> u8v {
        return ((x >> shift) & mask) | ((x & mask) << shift);
    };
    auto reverse = [&](u8v x) -> u8v {  // sampling.reverse_bits
        x = swap_bits(x, 0x55555555u, 1u);
        x = swap_bits(x, 0x33333333u, 2u);
        x = swap_bits(x, 0x0F0F0F0Fu, 4u);
        x = swap_bits(x, 0x00FF00FFu, 8u);
        return (x >> 16u) | (x << 16u);
    };
    auto laine_karras = [](u8v x, unsigned seed) -> u8v {
        x = x + seed;
        x = x ^ (x * 0x6C50B47Cu);
        x = x ^ (x * 0xB82F1E52u);
        x = x ^ (x * 0xC7AFE638u);
        x = x ^ (x * 0x8D22F6E6u);
        return x;
    };
    auto fold_down = [](u8v x, unsigned mask, unsigned shift) -> u8v {
        return x ^ ((x >> shift) & mask);
    };
    auto to_unit = [](u8v x) -> f8v {  // 24 bits: exact as int32 and as float
        return __builtin_convertvector((i8v)(x >> 8u), f8v) * 5.9604645e-08f;
    };
    auto broadcast = [](unsigned x) -> u8v { return (u8v){} + x; };
    // sample_2d_at(sampler, seed, k): the point's two coordinates
    auto sample_2d = [&](u8v k, unsigned seed, f8v& x, f8v& y) {
        if (sampler == 1) {
            u8v dim1 = fold_down(k, 0x55555555u, 1u);
            dim1 = fold_down(dim1, 0x33333333u, 2u);
            dim1 = fold_down(dim1, 0x0F0F0F0Fu, 4u);
            dim1 = fold_down(dim1, 0x00FF00FFu, 8u);
            dim1 = fold_down(dim1, 0x0000FFFFu, 16u);
            x = to_unit(reverse(laine_karras(k, seed)));
            y = to_unit(reverse(laine_karras(dim1, pcg(broadcast(seed))[0])));
        } else {
            const u8v h = pcg(broadcast(seed) ^ pcg(k));
            x = to_unit(h);
            y = to_unit(pcg(h));
        }
    };
    const int size = table.shape[0];
    auto table_read = [&](f8v u) -> f8v {  // film.table_read (u in [0, 1): its clamp a no-op)
        f8v out;
        for (int k = 0; k < 8; ++k) {
            const float x = u[k] * (float)(size - 1);
            int index = (int)x;
            index = index < size - 1 ? index : size - 1;
            const int next = index + 1 < size - 1 ? index + 1 : size - 1;
            const float t = x - (float)index;
            out[k] = (1.0f - t) * table.data[index] + t * table.data[next];
        }
        return out;
    };
    // decorrelated_2d(sampler, key, FILTER_KEY, i): the filter's seed, its index scramble's
    const unsigned seed = pcg(broadcast(key ^ FILTER_KEY_VALUE))[0];
    const unsigned seed2 = pcg(broadcast(seed))[0];
    const float* r = &rotation.data[0][0];
    for (int g = 0; g < count; g += 8) {
        u8v index;
        for (int k = 0; k < 8; ++k)
            index[k] = (unsigned)(first + g + k);
        const int n = count - g < 8 ? count - g : 8;
        f8v ux, uy;
        sample_2d(index, key, ux, uy);
        for (int k = 0; k < n; ++k)
            points.data[first_ray + g + k] = wp::vec2(ux[k], uy[k]);
        if (!pinhole)
            continue;
        // owen_scramble(i, seed2), then sample_2d_at(sampler, seed, that): the offset
        f8v fx, fy;
        sample_2d(reverse(laine_karras(reverse(index), seed2)), seed, fx, fy);
        const f8v px = (float)col + table_read(fx);
        const f8v py = (float)row + table_read(fy);
        // camera_ray's raster plane and its PERSP pinhole ray
        const f8v x = (px - centre.c[0]) * step.c[0] + offset.c[0];
        const f8v y = (py - centre.c[1]) * step.c[1] + offset.c[1];
        const f8v wx = r[0] * x + r[1] * y + r[2] * -1.0f;
        const f8v wy = r[3] * x + r[4] * y + r[5] * -1.0f;
        const f8v wz = r[6] * x + r[7] * y + r[8] * -1.0f;
        const f8v squares = wx * wx + wy * wy + wz * wz;
        for (int k = 0; k < n; ++k) {
            const float length = __builtin_sqrtf(squares[k]);
            const int i = first_ray + g + k;
            origins.data[i] = position;
            directions.data[i] = wp::vec3(wx[k] / length, wy[k] / length, wz[k] / length);
            tmin.data[i] = clip_start * length;
            tmax.data[i] = clip_end * length;
        }
    }
};
run();
return pinhole ? 1 : 0;
