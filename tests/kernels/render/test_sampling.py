"""The samplers' points (kernels/render/sampling.py) against their definitions, computed in
numpy: Owen-scrambled Sobol points (Burley 2020, listings 3 and 4: scramble(d, s) =
reverse(laine_karras(reverse(d), s))) of the first two Sobol dimensions, the first scrambled
with the pixel's key, the second with pcg_hash of it. The device code skips the reversals
that cancel; this spells every one out."""

from __future__ import annotations

import numpy as np
import warp as wp
from scenesort.kernels.render.sampling import (
    SAMPLERS,
    pixel_key,
    sample_2d_at,
    sobol_dim1_reversed,
)

U32 = np.uint64(0xFFFFFFFF)
LK = (0x6C50B47C, 0xB82F1E52, 0xC7AFE638, 0x8D22F6E6)


def reverse(x: np.ndarray) -> np.ndarray:
    bits = (x[:, None] >> np.arange(32, dtype=np.uint64)) & np.uint64(1)
    return (bits << np.arange(31, -1, -1, dtype=np.uint64)).sum(axis=1, dtype=np.uint64)


def laine_karras(x: np.ndarray, seed: np.ndarray) -> np.ndarray:
    x = (x + seed) & U32
    for c in LK:
        x = x ^ ((x * np.uint64(c)) & U32)
    return x


def pcg(x: np.ndarray) -> np.ndarray:
    state = (x * np.uint64(747796405) + np.uint64(2891336453)) & U32
    word = (((state >> ((state >> np.uint64(28)) + np.uint64(4))) ^ state)
            * np.uint64(277803737)) & U32
    return (word >> np.uint64(22)) ^ word


def sobol_dim1(index: np.ndarray) -> np.ndarray:
    """Direction numbers of the second dimension: v_0 = 2^31, v_{b+1} = v_b ^ (v_b >> 1)."""
    out = np.zeros_like(index)
    v = np.uint64(1 << 31)
    for b in range(32):
        out ^= np.where((index >> np.uint64(b)) & np.uint64(1), v, np.uint64(0))
        v ^= v >> np.uint64(1)
    return out


def scramble(x: np.ndarray, seed: np.ndarray) -> np.ndarray:
    return reverse(laine_karras(reverse(x), seed))


@wp.kernel
def _points(keys: wp.array(dtype=wp.uint32), indices: wp.array(dtype=wp.uint32),
            out: wp.array(dtype=wp.vec2)):
    i = wp.tid()
    out[i] = sample_2d_at(1, keys[i], indices[i])


@wp.kernel
def _keys(pixels: wp.array(dtype=int), seed: int, out: wp.array(dtype=wp.uint32)):
    i = wp.tid()
    out[i] = pixel_key(pixels[i], seed)


def test_sobol_points_are_owen_scrambled_sobol(device):
    rng = np.random.default_rng(7)
    n = 20000
    pixels = rng.integers(0, 1 << 22, n)
    keys = wp.empty(n, dtype=wp.uint32, device=device)
    wp.launch(_keys, dim=n, inputs=[wp.array(pixels, dtype=int, device=device), 5, keys],
              device=device)
    # every index below 4096, and large ones (adaptive rounds reach 2^16 and beyond)
    indices = np.concatenate([np.arange(4096), rng.integers(0, 1 << 32, n - 4096)])
    out = wp.empty(n, dtype=wp.vec2, device=device)
    wp.launch(_points, dim=n, inputs=[keys, wp.array(indices.astype(np.uint32),
                                                     dtype=wp.uint32, device=device), out],
              device=device)
    k, idx = keys.numpy().astype(np.uint64), indices.astype(np.uint64)
    x = scramble(reverse(idx), k)
    y = scramble(sobol_dim1(idx), pcg(k))
    want = np.stack([x >> np.uint64(8), y >> np.uint64(8)], axis=1).astype(np.float64) * 2.0**-24
    np.testing.assert_array_equal(out.numpy(), want.astype(np.float32))
    assert SAMPLERS["sobol"] == 1


@wp.kernel
def _dim1_reversed(indices: wp.array(dtype=wp.uint32), out: wp.array(dtype=wp.uint32)):
    i = wp.tid()
    out[i] = sobol_dim1_reversed(indices[i])


def test_the_second_dimension_in_closed_form_is_the_direction_numbers_sum(device):
    """All 32 bits (the points keep 24 of them after the scramble), for every index below
    2^16 and random 32-bit ones (the film's Owen-scrambled indices)."""
    rng = np.random.default_rng(8)
    idx = np.concatenate([np.arange(1 << 16), rng.integers(0, 1 << 32, 1 << 16),
                          [0xFFFFFFFF, 0x80000000]]).astype(np.uint32)
    out = wp.empty(len(idx), dtype=wp.uint32, device=device)
    wp.launch(_dim1_reversed, dim=len(idx), inputs=[wp.array(idx, dtype=wp.uint32,
                                                             device=device), out],
              device=device)
    want = reverse(sobol_dim1(idx.astype(np.uint64))).astype(np.uint32)
    np.testing.assert_array_equal(out.numpy(), want)
