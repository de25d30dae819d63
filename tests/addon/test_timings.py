"""A build answer of the service fills the panel's timings and a bounded history."""

from __future__ import annotations

import bpy

from addon import timings
from addon.props import HISTORY_LENGTH


def _answer(method: str, leaf: int, total: float, cached: bool = False) -> dict:
    """The shape of `BvhInfo` in backend/wire/models.py."""
    return {
        "scene_id": "0" * 32,
        "method": method,
        "leaf_size": leaf,
        "cached": cached,
        "timings_ms": {"total": total, "split_plane": total * 0.5, "aabb": total * 0.25},
        "stats": {"nodes": 31, "leaves": 16, "depth": 5, "sah_cost": 42.5,
                  "triangles": 2_000_000, "degenerate": 0},
    }  # fmt: skip


def test_last_build_fields(registered: bpy.types.Scene) -> None:
    props = registered.scenesort
    timings.apply_build(props, _answer("sah", 8, 100.0), "sah", 8)
    assert props.has_build and not props.build_cached
    assert props.build_total_ms == 100.0 and props.build_triangles == 2_000_000
    assert props.build_nodes == 31 and props.build_sah_cost == 42.5
    assert abs(props.build_mtris_per_s - 20.0) < 1e-9  # 2M triangles in 0.1 s
    assert [(p.name, p.ms) for p in props.build_phases] == [("split_plane", 50.0), ("aabb", 25.0)]


def test_history_is_newest_first_bounded_and_skips_cached(registered: bpy.types.Scene) -> None:
    props = registered.scenesort
    for i in range(HISTORY_LENGTH + 3):
        timings.apply_build(props, _answer("median", i + 1, float(i)), "median", i + 1)
    timings.apply_build(props, _answer("median", 99, 1.0, cached=True), "median", 99)
    assert len(props.build_history) == HISTORY_LENGTH
    assert props.build_history[0].leaf_size == HISTORY_LENGTH + 3  # newest first
    assert props.build_cached and props.build_leaf_size == 99
    assert all(r.leaf_size != 99 for r in props.build_history)


def test_phases_replace_the_previous_build(registered: bpy.types.Scene) -> None:
    props = registered.scenesort
    timings.apply_build(props, _answer("sah", 8, 10.0), "sah", 8)
    answer = _answer("sah", 8, 10.0)
    answer["timings_ms"] = {"total": 5.0, "build": 5.0}
    timings.apply_build(props, answer, "sah", 8)
    assert [p.name for p in props.build_phases] == ["build"]


def test_compile_time_is_shown_apart_from_the_build(registered: bpy.types.Scene) -> None:
    """Warp's first-use compile time is in the answer but is neither a phase nor total."""
    props = registered.scenesort
    answer = _answer("sah", 8, 71.0)
    answer["timings_ms"]["compile"] = 7024.0
    timings.apply_build(props, answer, "sah", 8)
    assert props.build_total_ms == 71.0 and props.build_compile_ms == 7024.0
    assert "compile" not in [p.name for p in props.build_phases]
