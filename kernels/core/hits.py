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

    @property
    def hit(self) -> np.ndarray:
        return self.triangle >= 0
