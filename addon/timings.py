"""Write a build answer of the service into `scene.scenesort` (last build and history)."""

from __future__ import annotations

from typing import Any

from .props import HISTORY_LENGTH


def _number(source: dict, *names: str) -> float:
    for name in names:
        value = source.get(name)
        if isinstance(value, int | float) and not isinstance(value, bool):
            return float(value)
    return 0.0


NOT_PHASES = {"total", "phases", "phase_ms", "compile"}  # compile: Warp's, apart from the build


def phases(timings: dict[str, Any]) -> list[tuple[str, float]]:
    """Per-phase milliseconds from `timings_ms` (flat, or nested under 'phases')."""
    nested = timings.get("phases") or timings.get("phase_ms")
    source = nested if isinstance(nested, dict) else timings
    return [
        (str(name), float(ms))
        for name, ms in source.items()
        if name not in NOT_PHASES and isinstance(ms, int | float)
    ]


def apply_build(props: Any, answer: dict[str, Any], method: str, leaf_size: int) -> None:
    """Fill the last-build fields; a fresh (not cached) build also joins the history."""
    timings = answer.get("timings_ms") or {}
    stats = answer.get("stats") if isinstance(answer.get("stats"), dict) else answer
    total = _number(timings, "total") or _number(stats, "build_ms")
    triangles = int(_number(stats, "triangles") or _number(answer, "triangles"))
    props.has_build = True
    props.build_total_ms = total
    props.build_compile_ms = _number(timings, "compile") or _number(stats, "compile_ms")
    props.build_cached = bool(answer.get("cached", False))
    props.build_method = str(answer.get("method", method))
    props.build_leaf_size = int(answer.get("leaf_size", leaf_size))
    props.build_triangles = triangles
    props.build_nodes = int(_number(stats, "nodes"))
    props.build_sah_cost = _number(stats, "sah_cost")
    props.build_mtris_per_s = triangles / (total * 1e3) if total > 0 else 0.0
    props.build_phases.clear()
    for name, ms in phases(timings):
        item = props.build_phases.add()
        item.name, item.ms = name, ms
    if props.build_cached:
        return
    record = props.build_history.add()
    record.method, record.leaf_size = props.build_method, props.build_leaf_size
    record.triangles, record.total_ms = triangles, total
    props.build_history.move(len(props.build_history) - 1, 0)  # newest first
    while len(props.build_history) > HISTORY_LENGTH:
        props.build_history.remove(len(props.build_history) - 1)
