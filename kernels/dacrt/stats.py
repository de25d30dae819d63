"""What a `dacrt_trace` did and what it cost: pass a `DacrtStats()` as `stats=` to have it
filled."""

from __future__ import annotations

from dataclasses import dataclass, field

from ..core.record import Record, unset


@dataclass(slots=True)
class DacrtStats(Record):
    """A trace's statistics (docs/kernels-api.md); times in ms. The fields of the variant
    that did not run stay None."""

    variant: str = ""  # "pool" | "breadth_first"
    total_ms: float = 0.0
    trace_ms: float = 0.0
    compile_ms: float = 0.0  # Warp's, not in the other times
    # pool: SplitPlane, PPS1, Swap1, PPS2, Swap2, AABB, Intersect, Sort, Children (storing
    # children, activating dependants); breadth_first: filter, sort, reduce, children,
    # gather, intersect
    phase_ms: dict[str, float] = field(default_factory=dict)
    peak_bytes: int = 0  # device memory held at the peak
    degenerate: int = 0  # triangles without area: never tested
    # the task-pool variant (2012)
    split: str | None = unset()  # "rdh" | "median"
    prepare_ms: float | None = unset()
    tasks: int | None = unset()
    intersection_tasks: int | None = unset()
    depth: int | None = unset()
    rays_sorted: int | None = unset()
    tris_sorted: int | None = unset()
    pairs: int | None = unset()  # rays x triangles of the intersection tasks (to 1000)
    intersection_rays: int | None = unset()  # rays an intersection task met ...
    intersection_rays_skipped: int | None = unset()  # ... and those with no pair tested
    pool_slots_used: int | None = unset()
    workers: int | None = unset()
    small_items: int | None = unset()  # as used
    pool_capacity: int | None = unset()  # as used, after pool_retries overflows
    pool_retries: int | None = unset()
    # the breadth-first variant (2013)
    levels: int | None = unset()
    peak_nodes: int | None = unset()
