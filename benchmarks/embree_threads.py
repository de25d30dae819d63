"""embreex on as many threads as ours: a fair peer for a trace on several host threads.

`scene.run()` of embreex traces on the calling thread without the Python lock
(shared/WARP_FACTS.md: two Python threads, one half of the rays each, ran 1.5-1.9x one),
so the rays are cut into one contiguous share per thread and each share is traced on a
thread of its own, at once.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
from scenesort.backend.tools import peers


class ThreadedEmbree:
    """`peers.Embree` (the same scene for every thread count) traced on `threads` threads."""

    def __init__(self, vertices: np.ndarray, indices: np.ndarray, max_threads: int):
        self.embree = peers.Embree(vertices, indices)
        self.build_s = self.embree.build_s  # embreex's mesh copy included
        self.pool = ThreadPoolExecutor(max_threads)

    def _split(self, fn, o: np.ndarray, d: np.ndarray, threads: int) -> list:
        cuts = np.linspace(0, len(o), threads + 1).astype(int)
        shares = [self.pool.submit(fn, o[a:b], d[a:b])
                  for a, b in zip(cuts[:-1], cuts[1:], strict=True)]
        return [s.result() for s in shares]

    def closest(self, o: np.ndarray, d: np.ndarray, threads: int) -> np.ndarray:
        """The triangle hit by each ray (-1: none)."""
        return np.concatenate([tri for _, tri in self._split(self.embree.closest, o, d,
                                                             threads)])

    def occluded(self, o: np.ndarray, d: np.ndarray, tmax: float, threads: int) -> np.ndarray:
        return np.concatenate(self._split(lambda a, b: self.embree.occluded(a, b, tmax), o, d,
                                          threads))
