"""The add-on's AO settings are the engine's (scenesort/ao_options.py): its generated copy,
addon/ao_options.py, is what `scenesort addon-options` writes now, and the properties take
their defaults, ranges and choices from it."""

from __future__ import annotations

import bpy
from scenesort.backend.tools import addon_options

from addon import export
from scenesort.ao_options import AO_OPTIONS, AoOptions


def test_the_table_is_what_the_command_writes_now() -> None:
    assert not addon_options.stale(), (
        "addon/ao_options.py differs from AO_OPTIONS: run `scenesort addon-options`")


def test_the_properties_take_the_definitions_bounds(registered: bpy.types.Scene) -> None:
    rna = registered.scenesort.bl_rna.properties
    spp = AO_OPTIONS["spp"]
    assert (rna["spp"].default, rna["spp"].hard_min, rna["spp"].hard_max) == (
        spp.default, spp.low, spp.soft_high)
    for name in ("target_error", "max_pixel_error"):  # 0: unset; below the excluded 1
        spec = AO_OPTIONS[name]
        assert spec.optional and spec.low_open and spec.high_open
        assert rna[name].default == rna[name].hard_min == spec.low
        assert spec.low < rna[name].hard_max < spec.high
    distance = AO_OPTIONS["distance"]
    assert rna["ao_distance"].default == rna["ao_distance"].hard_min == distance.low
    seed = AO_OPTIONS["seed"]
    assert (rna["seed"].default, rna["seed"].hard_min, rna["seed"].hard_max) == (
        seed.default, seed.low, seed.high)
    engine = AO_OPTIONS["engine"]
    assert tuple(i.identifier for i in rna["engine"].enum_items) == engine.choices
    assert rna["engine"].default == engine.default
    assert AoOptions().terminator_offset == export.DEFAULT_TERMINATOR_OFFSET
