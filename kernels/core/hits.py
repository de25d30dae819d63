"""The answer of every tracer: closest (or any) hit per ray, as numpy arrays."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Hits:
    t: np.ndarray  # (R,) float32, inf on a miss
    triangle: np.ndarray  # (R,) int32, -1 on a miss
    u: np.ndarray  # (R,) float32 weight of v1
    v: np.ndarray  # (R,) float32 weight of v2
    # (R,) int32 instance of a two-level scene's hit, -1 on a miss; for a single mesh 0
    # where it hits (the mesh is its own one instance), made when first read (below)
    instance: np.ndarray | None = None

    @property
    def hit(self) -> np.ndarray:
        return self.triangle >= 0


def _instance(self: Hits) -> np.ndarray:
    # a single mesh's: -1 -> -1, k >= 0 -> 0, the sign (4x faster than a where); made on
    # first read, not by every trace (~1 ms of a million cheap AO rays on two threads)
    if self._instance is None:
        self._instance = np.right_shift(self.triangle, 31).astype(np.int32, copy=False)
    return self._instance


def _set_instance(self: Hits, value: np.ndarray | None) -> None:
    self._instance = value


# after @dataclass, which took the field's default (None) for __init__
Hits.instance = property(_instance, _set_instance)
