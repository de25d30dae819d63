"""What a BVH build made and what it cost (`Bvh.stats`); `refit_bvh` adds its figures."""

from __future__ import annotations

from dataclasses import dataclass

from ..core.record import Record, unset


@dataclass(frozen=True, slots=True)
class BvhStats(Record):
    """A build's statistics (docs/kernels-api.md); times in ms."""

    action: str  # "build"; refit_bvh: "refit" or "rebuild"
    build_ms: float  # the build's wall time, Warp's compile time not in it
    compile_ms: float  # Warp's: seconds on first use, then ~ms (a refit's, after a refit)
    # validate, prepare, SplitPlane, PPS, Swap, AABB, Nodes, reorder, collapse (what the
    # collapse adds after the reorder, beside which its serial start runs); a refit's:
    # validate, triangles, nodes
    phase_ms: dict[str, float]
    nodes: int  # binary nodes
    leaves: int
    depth: int
    sah_cost: float  # traversal and intersection cost 1 (after a refit: the refit tree's)
    triangles: int  # the input's, degenerate ones included
    degenerate: int  # triangles without area: left out of the tree
    pool_slots_used: int
    pool_steps_published: int  # steps handed to the pool (not run inline)
    workers: int
    method: str  # "sah" | "median"
    leaf_size: int
    width: int  # the tree traversed: 2 if a wide tree would need more than WIDE_STACK
    wide_nodes: int
    wide_stack: int  # most stack entries the wide traversal holds
    leaf_blocks: int  # 4-triangle blocks of the wide leaves
    bvh_bytes: int  # what the tree keeps allocated: nodes, leaf-order triangles and their
    # ids, wide nodes and leaf blocks (the mesh's own arrays not counted)
    device: str
    # refit_bvh: the refit tree's SAH cost over the last build's, that build's cost, the
    # refit's wall time (before a rebuild too), and why it rebuilt ("sah" | "area")
    sah_ratio: float | None = unset()
    build_sah_cost: float | None = unset()
    refit_ms: float | None = unset()
    rebuild_reason: str | None = unset()
