"""The Film's pixel filter as Cycles samples it: a sub-pixel position per camera sample,
importance-sampled over the filter (`filter_table`, `filter_position`).

Cycles (intern/cycles/scene/film.cpp, util/math_cdf.cpp, kernel/camera/camera.h) does not
weight samples by the filter: each camera ray starts at a raster position drawn from the
filter's own distribution, and every sample counts with weight 1. The filter is separable:
x and y are drawn independently from one 1D inverted CDF table of FILTER_TABLE_SIZE entries,
read with linear interpolation. Built as Cycles builds it:

- the profile, in the filter's own coordinate v >= 0 and its table width w:
  BOX 1; GAUSSIAN exp(-2 (6 v / w)^2) with w = 3 * width; BLACKMAN_HARRIS
  0.35875 - 0.48829 cos(a) + 0.14128 cos(2a) - 0.01168 cos(3a), a = 2 pi (v / w + 0.5),
  with w = 2 * width (`width` is the scene's `filter_width`, in pixels);
- its CDF over v in [0, w / 2] at FILTER_TABLE_SIZE - 1 points, inverted symmetrically: the
  table maps u in [0, 1] to a raster offset 0.5 +- v from the pixel's corner, so a pixel's
  samples spread over [-w/2, w/2] pixels about its centre (Blackman-Harris 1.5: +-1.5 px,
  the lobe's tails; Gaussian 1.5: sigma 0.375 px; Box 1: the pixel itself).

The sub-pixel pair of sample i is a point of the pixel's Owen-scrambled Sobol sequence with
its own scramble key and a shuffled index (Burley 2020, sec. 4), so it is stratified over
the samples as the occlusion directions are, and decorrelated from them.

One difference from Cycles, on purpose: Cycles' camera (integrate_camera_sample) puts
sample 0 at u = (0.5, 0.5), the pixel's centre, for the first viewport sample's sake; that
gives the centre a weight of 1/N on top of the filter (the converged value then depends on
N) and takes a point out of the pixel's Sobol net. Here every sample is drawn from the
filter. At N = 64 the measured parity (docs/kernels-api.md) shows no effect of it.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from scenesort.ao_options import AO_OPTIONS, OptionError

from ..core.compile_options import MODULE_OPTIONS
from .sampling import owen_scramble, pcg_hash, sample_2d_at

wp.set_module_options(MODULE_OPTIONS)

FILTER_TABLE_SIZE = 1024  # Cycles' FILTER_TABLE_SIZE
FILTER_KEY = wp.constant(wp.uint32(0x2545F491))  # separates the filter's scramble from AO's


def _table_width(kind: str, width: float) -> float:
    """The support w of Cycles' table for a filter of `width` pixels (film.cpp)."""
    return {"BOX": 1.0, "GAUSSIAN": 3.0, "BLACKMAN_HARRIS": 2.0}[kind] * width


def filter_reach(kind: str, width: float) -> float:
    """How far, in pixels, a pixel's samples reach outside it: w / 2 - 1/2 (0 for no
    filter), what culling must keep beyond the image's edges (cull.view_planes)."""
    return max(0.0, 0.5 * _table_width(kind, width) - 0.5) if width > 0 else 0.0


def filter_profile(kind: str, width: float, v: np.ndarray) -> np.ndarray:
    """The filter's unnormalised weight at raster offsets `v` (pixels from the centre);
    0 outside the table's support [-w/2, w/2]."""
    check_filter(kind, width)
    w = _table_width(kind, width)
    v = np.abs(np.asarray(v, dtype=np.float64))
    if kind == "BOX":
        y = np.ones_like(v)
    elif kind == "GAUSSIAN":
        y = np.exp(-2.0 * (6.0 * v / w) ** 2)
    else:
        a = 2.0 * math.pi * (v / w + 0.5)
        y = 0.35875 - 0.48829 * np.cos(a) + 0.14128 * np.cos(2 * a) - 0.01168 * np.cos(3 * a)
    return np.where(v <= 0.5 * w, y, 0.0)


def check_filter(kind: str, width: float) -> None:
    """Raise OptionError (a ValueError) naming `pixel_filter` or `filter_width` when either
    is not AoOptions' (the one definition of both) or the width is 0 (no filter)."""
    AO_OPTIONS["pixel_filter"].check(kind)
    if AO_OPTIONS["filter_width"].check(width) == 0.0:
        raise OptionError("filter_width", "a pixel filter needs filter_width > 0 (0 renders "
                          "pixel centres, without a filter)", "set filter_width > 0")


def filter_table(kind: str, width: float) -> np.ndarray:
    """Cycles' importance-sampling table (float32, (FILTER_TABLE_SIZE,)): entry k is the
    raster offset from the pixel's corner for u = k / (FILTER_TABLE_SIZE - 1)."""
    check_filter(kind, width)
    n = FILTER_TABLE_SIZE
    half = 0.5 * _table_width(kind, width)
    # math_cdf.cpp, cdf_evaluate(n - 1, 0, half): n - 1 samples of |f|, summed, normalised.
    v = half * np.arange(n - 1, dtype=np.float64) / (n - 2)
    cdf = np.concatenate(([0.0], np.cumsum(np.abs(filter_profile(kind, width, v)))))
    cdf /= cdf[-1]
    # cdf_invert(make_symmetric): half the table inverts the CDF of |v|, mirrored about 0.5.
    half_size = (n - 1) // 2
    x = np.arange(half_size + 1, dtype=np.float64) / half_size
    index = np.searchsorted(cdf, x, side="right")  # std::upper_bound
    inside = index < cdf.size - 1
    i = np.where(inside, index, cdf.size - 1)
    nxt = np.minimum(i + 1, cdf.size - 1)
    t = np.where(inside, (x - cdf[i]) / np.where(inside, cdf[nxt] - cdf[i], 1.0), 0.0)
    y = (i + t) / (n - 1) * 2.0 * half
    table = np.empty(n, dtype=np.float64)
    table[half_size : 2 * half_size + 1] = 0.5 * (1.0 + y)
    table[half_size::-1] = 0.5 * (1.0 - y)
    # n is even, so one entry is left: Cycles leaves it 0, which sends the top 1/1023 of u
    # towards the pixel's corner; the edge value repeated keeps those samples on the profile.
    table[2 * half_size + 1 :] = table[2 * half_size]
    return table.astype(np.float32)


@wp.func
def table_read(table: wp.array(dtype=float), u: float) -> float:
    """Cycles' lookup_table_read: the table at u in [0, 1], linearly interpolated."""
    size = table.shape[0]
    x = wp.clamp(u, 0.0, 1.0) * float(size - 1)
    index = wp.min(int(x), size - 1)
    nindex = wp.min(index + 1, size - 1)
    t = x - float(index)
    return (1.0 - t) * table[index] + t * table[nindex]


@wp.func
def filter_position(
    table: wp.array(dtype=float), sampler: int, key: wp.uint32, index: int
) -> wp.vec2:
    """Sample `index`'s raster offset (x right, y down) from the corner of the pixel whose
    occlusion samples use `key`."""
    u = decorrelated_2d(sampler, key, FILTER_KEY, index)
    return wp.vec2(table_read(table, u[0]), table_read(table, u[1]))


@wp.func
def decorrelated_2d(sampler: int, key: wp.uint32, salt: wp.uint32, index: int) -> wp.vec2:
    """Point `index` of the pixel's 2D sequence (of the pixel whose occlusion samples use
    `key`) under its own scramble `salt`, decorrelated from the occlusion directions' and
    from every other salt's: the filter's sub-pixel positions, the lens's points."""
    seed = pcg_hash(key ^ salt)
    # Burley 2020 (JCGT 9(4)), sec. 4: the index is Owen-scrambled too, else point i here
    # and the occlusion direction's point i share their strata (the same Sobol
    # dimensions under two scrambles: the top bits agree or differ for every sample of a
    # pixel) and each pixel's estimate keeps a bias that more samples never remove. The
    # first 2^m indices go to an aligned block of 2^m, which is still a (0, m, 2)-net.
    return sample_2d_at(sampler, seed, owen_scramble(wp.uint32(index), pcg_hash(seed)))
