"""DACRT's tuning: one frozen dataclass, device-dependent defaults, keywords and errors."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp
from scenesort.kernels import DacrtStats, dacrt_trace
from scenesort.kernels.dacrt import DacrtOptions
from scenesort.kernels.dacrt.options import DEVICE_DEFAULTS

from ..reference import random_rays, random_soup


class _Cuda:  # what for_device reads of a device
    is_cpu = False


@pytest.mark.host_only
def test_device_defaults_fill_only_what_is_left_open():
    cpu = DacrtOptions().for_device(wp.get_device("cpu"))
    assert (cpu.c_sort, cpu.min_rays, cpu.alpha, cpu.beta) == (4.0, 16, 32, 128)
    cuda = DacrtOptions().for_device(_Cuda())
    assert (cuda.c_sort, cuda.min_rays, cuda.alpha, cuda.beta) == (80.0, 32, 256, 256)
    mine = DacrtOptions(c_sort=10.0, alpha=7).for_device(wp.get_device("cpu"))
    assert (mine.c_sort, mine.min_rays, mine.alpha, mine.beta) == (10.0, 16, 7, 128)
    assert set(DEVICE_DEFAULTS["cpu"]) == set(DEVICE_DEFAULTS["cuda"])


@pytest.mark.host_only
def test_options_are_frozen_and_checked():
    opts = DacrtOptions()
    with pytest.raises(dataclasses.FrozenInstanceError):
        opts.c_sort = 1.0  # type: ignore[misc]
    with pytest.raises(ValueError, match="min_chunks"):
        DacrtOptions(min_chunks=0)
    with pytest.raises(ValueError, match="alpha and beta"):
        DacrtOptions(beta=0)
    with pytest.raises(TypeError, match="unknown DACRT option"):
        opts.with_(c_srot=4.0)
    assert opts.with_(c_sort=None) == opts  # a keyword left None changes nothing


def test_keywords_and_options_give_the_same_trace():
    rng = np.random.default_rng(6)
    v, f = random_soup(rng, 1500)
    o, d = random_rays(rng, 2000, -0.5, 1.5)
    by_keywords = dacrt_trace(v, f, o, d, c_sort=80.0, min_rays=32, rdh_min_rays=16)
    opts = DacrtOptions(c_sort=80.0, min_rays=32, rdh_min_rays=16)
    stats = DacrtStats()
    by_options = dacrt_trace(v, f, o, d, options=opts, stats=stats)
    assert np.array_equal(by_keywords.triangle, by_options.triangle)
    assert np.array_equal(by_keywords.t, by_options.t)
    overridden = dacrt_trace(v, f, o, d, options=opts, small_items=0, stats=stats)
    assert stats.small_items == 0 and np.array_equal(overridden.t, by_options.t)
    with pytest.raises(TypeError, match="unknown DACRT option"):
        dacrt_trace(v, f, o, d, csort=4.0)
