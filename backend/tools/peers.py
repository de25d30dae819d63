"""Reference tracers to compare against in the same run: Warp's own `wp.Mesh` and Embree.

Each peer builds once and traces numpy rays; `closest` returns (t, triangle) with inf / -1
on a miss, `occluded` a bool per ray. Used by `scenesort bench` and the benchmarks.
Embree comes from `embreex` (the dev extra); `embree_available()` says whether it is here.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import warp as wp
from scenesort.kernels.core import Claims, claimed_items, launch_claimed

wp.set_module_options({"enable_backward": False})

# Warp's CPU builders ("lbvh" is GPU only: on CPU Warp warns and builds "sah" instead).
MESH_CONSTRUCTORS = ("sah", "median", "cubql")


@wp.kernel
def _mesh_closest(mesh: wp.uint64, o: wp.array(dtype=wp.vec3), d: wp.array(dtype=wp.vec3),
                  tmax: float, out_t: wp.array(dtype=float), out_tri: wp.array(dtype=int),
                  claims: Claims):
    items = claimed_items(claims, wp.tid())
    for i in range(items[0], items[1]):
        q = wp.mesh_query_ray(mesh, o[i], d[i], tmax)
        out_t[i] = wp.where(q.result, q.t, wp.inf)
        out_tri[i] = wp.where(q.result, q.face, -1)


@wp.kernel
def _mesh_occluded(mesh: wp.uint64, o: wp.array(dtype=wp.vec3), d: wp.array(dtype=wp.vec3),
                   tmax: float, out: wp.array(dtype=int), claims: Claims):
    items = claimed_items(claims, wp.tid())
    for i in range(items[0], items[1]):
        out[i] = wp.where(wp.mesh_query_ray_anyhit(mesh, o[i], d[i], tmax), 1, 0)


class WarpMesh:
    """`wp.Mesh` with `mesh_query_ray` / `mesh_query_ray_anyhit` (CPU)."""

    def __init__(self, vertices: np.ndarray, indices: np.ndarray, constructor: str = "sah",
                 leaf_size: int | None = None):
        self.name = f"wp.Mesh {constructor}"
        self.device = wp.get_device("cpu")
        self._points = wp.array(vertices, dtype=wp.vec3, device=self.device)
        self._indices = wp.array(np.ascontiguousarray(indices).ravel(), dtype=int,
                                 device=self.device)
        start = time.perf_counter()
        self.mesh = wp.Mesh(points=self._points, indices=self._indices,
                            bvh_constructor=constructor, bvh_leaf_size=leaf_size)
        self.build_s = time.perf_counter() - start

    def closest(self, o: np.ndarray, d: np.ndarray, tmax: float = 1e30,
                threads: int = 1) -> tuple[np.ndarray, np.ndarray]:
        t, tri = np.empty(len(o), np.float32), np.empty(len(o), np.int32)
        launch_claimed(_mesh_closest, len(o), [self.mesh.id, *self._rays(o, d), float(tmax), t,
                                               tri], self.device, threads)
        return t, tri

    def occluded(self, o: np.ndarray, d: np.ndarray, tmax: float,
                 threads: int = 1) -> np.ndarray:
        out = np.empty(len(o), np.int32)
        launch_claimed(_mesh_occluded, len(o), [self.mesh.id, *self._rays(o, d), float(tmax),
                                                out], self.device, threads)
        return out.astype(bool)

    def _rays(self, o: np.ndarray, d: np.ndarray) -> list[np.ndarray]:
        return [np.ascontiguousarray(x, np.float32) for x in (o, d)]


def embree_available() -> bool:
    try:
        import embreex  # noqa: F401
    except ImportError:
        return False
    return True


class Embree:
    """Embree 4 through `embreex` (one thread: embreex serialises calls). Its `tnear` is 0."""

    name = "Embree"

    def __init__(self, vertices: np.ndarray, indices: np.ndarray):
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        start = time.perf_counter()
        self.scene = rtcore_scene.EmbreeScene()
        TriangleMesh(self.scene, vertices, indices)
        self.scene.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32))  # commit
        self.build_s = time.perf_counter() - start  # includes embreex's slow mesh copy

    def closest(self, o: np.ndarray, d: np.ndarray, tmax: float = 1e30,
                threads: int = 1) -> tuple[np.ndarray, np.ndarray]:
        res = self.scene.run(o, d, dists=np.full(len(o), tmax, np.float32), output=1)
        tri = res["primID"].astype(np.int32)
        return np.where(tri >= 0, res["tfar"], np.inf).astype(np.float32), tri

    def occluded(self, o: np.ndarray, d: np.ndarray, tmax: float,
                 threads: int = 1) -> np.ndarray:
        # dists is overwritten in place by embreex; 0 means occluded, -1 not.
        res = self.scene.run(o, d, dists=np.full(len(o), tmax, np.float32), query="OCCLUDED")
        return np.asarray(res) == 0


def timeit(fn: Callable[[], object], repeat: int = 5, warmup: int = 1) -> float:
    """Median wall seconds of `repeat` calls after `warmup` calls (device synchronised)."""
    return timeit_each([fn], repeat, warmup)[0]


def timeit_each(fns: list[Callable[[], object]], repeat: int = 5,
                warmup: int = 1, before: Callable[[], object] | None = None) -> list[float]:
    """Median wall seconds of each function of `samples_each`."""
    return [float(np.median(t)) for t in samples_each(fns, repeat, warmup, before)]


def samples_each(fns: list[Callable[[], object]], repeat: int = 5, warmup: int = 1,
                 before: Callable[[], object] | None = None) -> list[list[float]]:
    """Wall seconds of each function, called in turn `repeat` times after `warmup` rounds:
    interleaved, so that a burst of load on a shared machine hits all of them alike, and in
    reverse order every other round, so that none always runs after the same one (on the
    VM of docs/benchmarks.md a call's time depends on what ran before it). `before`
    (untimed) runs before every timed call."""
    for _ in range(warmup):
        for fn in fns:
            fn()
    times: list[list[float]] = [[] for _ in fns]
    for k in range(repeat):
        order = range(len(fns)) if k % 2 == 0 else reversed(range(len(fns)))
        for i in order:
            if before is not None:
                before()
            start = time.perf_counter()
            fns[i]()
            wp.synchronize_device("cpu")
            times[i].append(time.perf_counter() - start)
    return times


def random_rays(bounds: np.ndarray, count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Rays with origins uniform in the scene box and uniformly random directions."""
    rng = np.random.default_rng(seed)
    lo, hi = bounds
    o = (lo + (hi - lo) * rng.random((count, 3))).astype(np.float32)
    d = rng.normal(size=(count, 3))
    return o, (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)


def ao_rays(vertices: np.ndarray, indices: np.ndarray, o: np.ndarray, d: np.ndarray,
            t: np.ndarray, tri: np.ndarray, per_hit: int = 7,
            seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """`per_hit` cosine-weighted directions about the geometric normal (turned toward the
    viewer) at each primary hit; origins pushed off the surface by a small relative offset."""
    hit = tri >= 0
    p = o[hit].astype(np.float64) + t[hit, None] * d[hit]
    v = vertices[indices[tri[hit]]].astype(np.float64)
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n *= -np.sign(np.einsum("ij,ij->i", n, d[hit]))[:, None]
    rng = np.random.default_rng(seed)
    k = len(p) * per_hit
    u1, u2 = rng.random(k), rng.random(k)
    r, phi = np.sqrt(u1), 2 * np.pi * u2
    local = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1 - u1)], axis=1)
    nn = np.repeat(n, per_hit, axis=0)
    a = np.where(np.abs(nn[:, :1]) > 0.9, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    tx = np.cross(nn, a)
    tx /= np.linalg.norm(tx, axis=1, keepdims=True)
    ty = np.cross(nn, tx)
    dirs = local[:, :1] * tx + local[:, 1:2] * ty + local[:, 2:] * nn
    scale = np.maximum(np.abs(p).max(axis=1, keepdims=True), 1.0)
    origins = np.repeat(p + 1e-4 * scale * n, per_hit, axis=0)
    return origins.astype(np.float32), dirs.astype(np.float32)
