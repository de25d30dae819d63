"""AoOptions: every AO setting defined, documented and checked once, its bounds as data."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scenesort.kernels.render import AO_OPTIONS, AoOptions
from scenesort.kernels.render.sampling import SAMPLERS

from scenesort import kernels

pytestmark = pytest.mark.host_only  # host-side checks (the render runs on the CPU)


def test_every_field_is_in_the_table_with_its_default_and_doc():
    names = [f.name for f in dataclasses.fields(AoOptions)]
    assert list(AO_OPTIONS) == names
    defaults = AoOptions()
    for name, spec in AO_OPTIONS.items():
        assert spec.default == getattr(defaults, name) and spec.doc
        assert spec.check(spec.default) == spec.default


def test_the_table_says_what_each_setting_takes():
    assert AO_OPTIONS["spp"].kind is int and AO_OPTIONS["spp"].low == 1
    assert AO_OPTIONS["target_error"].optional and AO_OPTIONS["target_error"].low_open
    assert set(AO_OPTIONS["sampler"].choices) == set(SAMPLERS)
    assert AO_OPTIONS["engine"].choices == ("bvh", "dacrt")
    assert AO_OPTIONS["terminator_offset"].takes() == "a number in [0, 1]"
    assert AO_OPTIONS["target_error"].takes() == "a number in (0, 1) or None"


@pytest.mark.parametrize("changes,field", [
    ({"spp": 0}, "spp"), ({"spp": 2.0}, "spp"), ({"seed": -1}, "seed"),
    ({"seed": 2**31}, "seed"), ({"distance": np.nan}, "distance"),
    ({"terminator_offset": 1.5}, "terminator_offset"), ({"threads": 0}, "threads"),
    ({"denoise": 1}, "denoise"), ({"max_spp": 4, "target_error": 0.1}, "max_spp")])
def test_a_bad_value_names_the_field(changes, field):
    with pytest.raises(ValueError, match=field):
        AoOptions(**changes)


def test_numpy_scalars_become_python_numbers():
    opts = AoOptions(spp=np.int64(4), distance=np.float32(0.5))
    assert type(opts.spp) is int and type(opts.distance) is float and opts.distance == 0.5


def test_adaptive_minimum_and_copies():
    assert AoOptions(spp=2).min_spp == 2
    assert AoOptions(spp=2, target_error=0.1).min_spp == 8
    opts = AoOptions(target_error=0.1)
    assert opts.with_(target_error=None) == AoOptions()  # None means what it means
    with pytest.raises(TypeError, match=r"unknown AO option\(s\) \['sample'\]"):
        opts.with_(sample=4)


def test_options_and_keywords_render_the_same():
    """render_ao(options) and render_ao(**keywords) are one piece of code: the same image
    bit for bit; keywords change single fields of the options."""
    v = np.array([[-1, -1, 0], [1, -1, 0], [0, 1, 0], [0, 0, 0.3]], np.float32)
    f = np.array([[0, 1, 2], [0, 1, 3]], np.int32)
    bvh = kernels.build_bvh(v, f)
    o = np.tile(np.float32([[0.0, -0.2, 1.0]]), (16, 1))
    o[:, 0] += np.linspace(-0.5, 0.5, 16, dtype=np.float32)
    d = np.tile(np.float32([[0, 0, -1]]), (16, 1))
    opts = AoOptions(spp=8, seed=3, distance=2.0)
    a = kernels.render_ao(bvh, o, d, opts)
    b = kernels.render_ao(bvh, o, d, spp=8, seed=3, distance=2.0)
    c = kernels.render_ao(bvh, o, d, AoOptions(spp=8, seed=4), seed=3, distance=2.0)
    assert np.array_equal(a.ao, b.ao) and np.array_equal(a.ao, c.ao)
    assert np.array_equal(kernels.ambient_occlusion(bvh, o, d, opts), a.ao)
    with pytest.raises(TypeError, match="AoOptions"):
        kernels.render_ao(bvh, o, d, 8)


def test_a_filter_narrower_than_a_twentieth_of_a_pixel_renders_pixel_centres() -> None:
    """Cycles' narrowest filter (0.01 px, its 'no filter') would cost a camera ray per
    sample for samples within 1/20 px of the centre: it renders pixel centres, and says so."""
    from scenesort.ao_options import CENTRE_FILTER_WIDTH

    narrow = AoOptions(pixel_filter="GAUSSIAN", filter_width=0.01)
    assert not narrow.filtered and narrow.film.startswith("pixel centres: a 0.01 px filter")
    assert not AoOptions(filter_width=CENTRE_FILTER_WIDTH).filtered
    wide = AoOptions(filter_width=0.06)
    assert wide.filtered and wide.film == "BLACKMAN_HARRIS 0.06 px"
