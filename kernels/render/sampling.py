"""Sample points for Monte Carlo integration on the device: hashes, Owen-scrambled Sobol
points in 2D, cosine-weighted hemisphere directions and an orthonormal frame per normal.

Every sample is a pure function of (pixel key, sample index), so results do not depend
on how the work is split between launches or threads. Both samplers give points that are
each uniformly distributed in [0,1)^2, so every estimator built on them stays unbiased.
"""

from __future__ import annotations

import warp as wp

from ..core.compile_options import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)

SAMPLER_RANDOM = wp.constant(0)
SAMPLER_SOBOL = wp.constant(1)
SAMPLERS: dict[str, int] = {"random": 0, "sobol": 1}

# Laine-Karras permutation constants (Burley 2020, JCGT 9(4), listing 3).
LK0 = wp.constant(wp.uint32(0x6C50B47C))
LK1 = wp.constant(wp.uint32(0xB82F1E52))
LK2 = wp.constant(wp.uint32(0xC7AFE638))
LK3 = wp.constant(wp.uint32(0x8D22F6E6))
# PCG hash constants (Jarzynski and Olano 2020, JCGT 9(3), "pcg").
PCG_MUL = wp.constant(wp.uint32(747796405))
PCG_INC = wp.constant(wp.uint32(2891336453))
PCG_OUT = wp.constant(wp.uint32(277803737))
GOLDEN = wp.constant(wp.uint32(0x9E3779B9))  # 2^32 / golden ratio: decorrelates seeds
TO_UNIT = wp.constant(5.9604645e-08)  # 2^-24: 24 random bits to a float in [0, 1)
MIN_COS = wp.constant(2.4414062e-04)  # 2^-12: keeps every direction strictly above the surface
QUARTER_PI = wp.constant(0.7853981633974483)


@wp.func
def pcg_hash(x: wp.uint32) -> wp.uint32:
    # Jarzynski and Olano 2020, sec. 2: one PCG step with an output permutation.
    state = x * PCG_MUL + PCG_INC
    word = ((state >> ((state >> wp.uint32(28)) + wp.uint32(4))) ^ state) * PCG_OUT
    return (word >> wp.uint32(22)) ^ word


@wp.func
def pixel_key(pixel: int, seed: int) -> wp.uint32:
    """The scramble key of one pixel for one seed."""
    return pcg_hash(wp.uint32(pixel) ^ pcg_hash(wp.uint32(seed) + GOLDEN))


@wp.func
def swap_bits(x: wp.uint32, mask: wp.uint32, shift: wp.uint32) -> wp.uint32:
    return ((x >> shift) & mask) | ((x & mask) << shift)


@wp.func
def reverse_bits(x: wp.uint32) -> wp.uint32:
    # Hacker's Delight 7-1: swap ever larger bit groups.
    x = swap_bits(x, wp.uint32(0x55555555), wp.uint32(1))
    x = swap_bits(x, wp.uint32(0x33333333), wp.uint32(2))
    x = swap_bits(x, wp.uint32(0x0F0F0F0F), wp.uint32(4))
    x = swap_bits(x, wp.uint32(0x00FF00FF), wp.uint32(8))
    return (x >> wp.uint32(16)) | (x << wp.uint32(16))


@wp.func
def laine_karras(x: wp.uint32, seed: wp.uint32) -> wp.uint32:
    # Burley 2020, listing 3: a hash in which each bit depends only on lower bits.
    x = x + seed
    x = x ^ (x * LK0)
    x = x ^ (x * LK1)
    x = x ^ (x * LK2)
    x = x ^ (x * LK3)
    return x


@wp.func
def owen_scramble(x: wp.uint32, seed: wp.uint32) -> wp.uint32:
    # Burley 2020, listing 4: nested uniform (Owen) scrambling of a 32-bit fraction.
    return reverse_bits(laine_karras(reverse_bits(x), seed))


@wp.func
def fold_down(x: wp.uint32, mask: wp.uint32, shift: wp.uint32) -> wp.uint32:
    return x ^ ((x >> shift) & mask)


@wp.func
def sobol_dim1_reversed(index: wp.uint32) -> wp.uint32:
    """The second Sobol dimension with its bits reversed (the first, reversed, is the
    index itself): what owen_scramble reverses first. Reversed, its direction numbers are
    the rows of Pascal's triangle mod 2 (v_0 = 1, v_k = v_(k-1) ^ (v_(k-1) << 1): bit j of
    v_k is C(k, j) mod 2, 1 exactly when j's bits are a subset of k's, by Lucas's theorem),
    so bit j of the point is the XOR of the index's bits k over every superset k of j:
    five fold steps, the same bits as XOR-ing v_k over the index's set bits, which took a
    loop of up to 32 data-dependent branches for an Owen-scrambled index (the film's
    filter positions: 34 ns a position that way, 12 ns this way)."""
    x = fold_down(index, wp.uint32(0x55555555), wp.uint32(1))
    x = fold_down(x, wp.uint32(0x33333333), wp.uint32(2))
    x = fold_down(x, wp.uint32(0x0F0F0F0F), wp.uint32(4))
    x = fold_down(x, wp.uint32(0x00FF00FF), wp.uint32(8))
    return fold_down(x, wp.uint32(0x0000FFFF), wp.uint32(16))


@wp.func
def to_unit(x: wp.uint32) -> float:
    return float(x >> wp.uint32(8)) * TO_UNIT


@wp.func
def sample_2d_at(sampler: int, key: wp.uint32, k: wp.uint32) -> wp.vec2:
    """Point k of the pixel's sequence (k a 32-bit position: a sample index, or film.py's
    shuffled one): independent hashes, or Owen-scrambled Sobol (each pixel its own
    scramble, so pixels are decorrelated and each point uniform). Callers pass the
    position themselves: a wrapper taking an int cost 1-2% of a one-thread AO render
    (benchmarks/paired.py, ao1)."""
    if sampler == SAMPLER_SOBOL:
        # owen_scramble(d, s) = reverse(laine_karras(reverse(d), s)) for the Sobol points'
        # dimensions d = reverse(k) and sobol_dim1(k), written without the reversals that
        # cancel (3 of the 4, ~6 ns a sample on CPU; the same bits)
        x = reverse_bits(laine_karras(k, key))
        y = reverse_bits(laine_karras(sobol_dim1_reversed(k), pcg_hash(key)))
        return wp.vec2(to_unit(x), to_unit(y))
    h = pcg_hash(key ^ pcg_hash(k))
    return wp.vec2(to_unit(h), to_unit(pcg_hash(h)))


@wp.func
def sin_cos(t: float) -> wp.vec2:
    """(sin t, cos t) for |t| <= pi/4 from Cephes' single-precision minimax polynomials
    (sinf.c, cosf.c), within 2 ulps. Not wp.sin/wp.cos: CUDA's and the CPU's libraries
    differ in the last ulp, which on an H200 flipped a grazing occlusion sample against the
    CPU (Sponza, 4 spp: a pixel one sample apart); additions and products, never
    contracted (core.compile_options), round the same on every device."""
    z = t * t
    s = ((-1.9515295891e-4 * z + 8.3321608736e-3) * z - 1.6666654611e-1) * z * t + t
    c = ((2.443315711809948e-5 * z - 1.388731625493765e-3) * z + 4.166664568298827e-2) * z * z
    return wp.vec2(s, c - 0.5 * z + 1.0)


@wp.func
def cosine_hemisphere(u: wp.vec2) -> wp.vec3:
    """Cosine-weighted direction around +z from a point in [0,1)^2; z > 0 always.

    Concentric disk mapping (Shirley and Chiu 1997; PBR 4th ed., A.5.1) lifted to the
    hemisphere (Malley's method, PBR A.5.3); it keeps the points' stratification."""
    ox = 2.0 * u[0] - 1.0
    oy = 2.0 * u[1] - 1.0
    x = float(0.0)
    y = float(0.0)
    if wp.abs(ox) > wp.abs(oy):  # theta = pi/4 oy/ox
        sc = sin_cos(QUARTER_PI * (oy / ox))
        x = ox * sc[1]
        y = ox * sc[0]
    elif oy != 0.0:  # theta = pi/2 - pi/4 ox/oy: cos theta = sin(pi/4 ox/oy), and so on
        sc = sin_cos(QUARTER_PI * (ox / oy))
        x = oy * sc[0]
        y = oy * sc[1]
    # Clamping z only moves directions within 2^-12 of the horizon (probability ~2^-24).
    z = wp.max(wp.sqrt(wp.max(1.0 - x * x - y * y, 0.0)), MIN_COS)
    return wp.vec3(x, y, z)


@wp.func
def frame_x(n: wp.vec3) -> wp.vec3:
    # Duff et al. 2017, "Building an orthonormal basis, revisited" (JCGT 6(1)), listing 3.
    s = wp.where(n[2] >= 0.0, 1.0, -1.0)
    a = -1.0 / (s + n[2])
    b = n[0] * n[1] * a
    return wp.vec3(1.0 + s * n[0] * n[0] * a, s * b, -s * n[0])


@wp.func
def frame_y(n: wp.vec3) -> wp.vec3:
    # Duff et al. 2017, listing 3 (second tangent).
    s = wp.where(n[2] >= 0.0, 1.0, -1.0)
    a = -1.0 / (s + n[2])
    b = n[0] * n[1] * a
    return wp.vec3(b, s + n[1] * n[1] * a, -n[1])


@wp.func
def cosine_about(n: wp.vec3, u: wp.vec2) -> wp.vec3:
    """The cosine-weighted unit direction about n that the point u of [0,1)^2 gives."""
    w = cosine_hemisphere(u)
    return frame_x(n) * w[0] + frame_y(n) * w[1] + n * w[2]


@wp.func
def cosine_direction(n: wp.vec3, sampler: int, key: wp.uint32, index: int) -> wp.vec3:
    """Sample `index` of the pixel with `key`: a cosine-weighted unit direction about n."""
    return cosine_about(n, sample_2d_at(sampler, key, wp.uint32(index)))
