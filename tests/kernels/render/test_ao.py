"""Ambient occlusion: analytic cases, an independent Embree reference, convergence rates,
adaptive sampling against its target, determinism, skipping and cancellation."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh
from scenesort.kernels import Camera
from scenesort.kernels.render.adaptive import EFFICIENCY_MIN

from scenesort import kernels
from tests.kernels.render.adaptive_reference import (
    Z95,
    allocation_key,
    half_width,
    sampler_efficiency,
)

SAMPLERS = ("random", "sobol")


def grid_plane(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The square [-1,1]^2 at z=0 as n x n cells of two triangles each."""
    a, b = np.meshgrid(np.linspace(-1, 1, n + 1), np.linspace(-1, 1, n + 1), indexing="ij")
    v = np.stack([a.ravel(), b.ravel(), np.zeros(a.size)], 1)
    i = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    p00, p10, p01, p11 = i[:-1, :-1], i[1:, :-1], i[:-1, 1:], i[1:, 1:]
    f = np.concatenate([np.stack([p00, p10, p11], -1), np.stack([p00, p11, p01], -1)])
    return v, f.reshape(-1, 3).astype(np.int32)


def exact_plane(shift: float, scale: float, slope: tuple[float, float]):
    """An 8 x 8 grid on the plane z = a x + b y, scaled and translated, whose float32
    vertices are exact (a power-of-two step), so the surface really is flat."""
    step = 2.0 ** np.floor(np.log2(scale / 4))
    v, f = grid_plane(8)
    v = 4 * v  # integer grid coordinates -4..4
    v[:, 2] = slope[0] * v[:, 0] + slope[1] * v[:, 1]
    v64 = shift + step * v
    assert np.array_equal(v64.astype(np.float32), v64), "plane not representable"
    return v64, f


@pytest.mark.parametrize("slope", [(0.5, 0.25), (4.0, -0.5)])
@pytest.mark.parametrize("shift,scale", [(0.0, 1.0), (1e4, 1.0), (0.0, 1e-3), (0.0, 1e3),
                                         (1e4, 1e3)])
def test_open_plane_is_exactly_one(shift, scale, slope):
    """A tilted, translated, scaled open plane never occludes itself: AO is exactly 1.0,
    seen from both sides and from grazing angles down to 2 degrees. (A plane 1e-3 across
    at 1e4 is not included: float32 cannot hold it, its ulp there is 1e-3.)"""
    rng = np.random.default_rng(1)
    v64, f = exact_plane(shift, scale, slope)
    bvh = kernels.build_bvh(v64.astype(np.float32), f)
    r = 400
    tri = f[rng.integers(0, len(f), r)]
    bary = rng.dirichlet([2.0, 2.0, 2.0], r)  # inside the triangle, rarely on an edge
    target = np.einsum("rk,rkj->rj", bary, v64[tri])
    normal = np.array([-slope[0], -slope[1], 1.0]) / np.linalg.norm([-slope[0], -slope[1], 1])
    t1 = np.cross(normal, [1.0, 0, 0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(normal, t1)
    elevation = np.radians(rng.uniform(2.0, 89.0, r)) * rng.choice([-1.0, 1.0], r)
    azimuth = rng.uniform(0, 2 * np.pi, r)
    back = (np.cos(elevation) * np.cos(azimuth))[:, None] * t1 + (
        np.cos(elevation) * np.sin(azimuth))[:, None] * t2 + np.sin(elevation)[:, None] * normal
    origins = (target + 2.0 * scale * back).astype(np.float32)
    directions = target - origins
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    for sampler in SAMPLERS:
        res = kernels.render_ao(bvh, origins, directions.astype(np.float32), spp=64,
                                distance=np.inf, sampler=sampler)
        assert np.all(res.spp_used == 64), "every primary ray must hit the plane"
        assert np.all(res.ao == 1.0), f"{int((res.ao < 1).sum())} pixels occluded themselves"


def wall_form_factor(point: np.ndarray, corners: np.ndarray) -> float:
    """Lambert's polygon formula: form factor from a differential area at `point` with
    normal +z to a polygon above its plane (Cohen and Wallace, Radiosity, eq. 4.26)."""
    r = corners - point
    total = 0.0
    for i in range(len(r)):
        a, b = r[i], r[(i + 1) % len(r)]
        c = np.cross(a, b)
        angle = np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))
        total += angle * c[2] / np.linalg.norm(c)
    return abs(total) / (2 * np.pi)


@pytest.mark.parametrize("sampler", SAMPLERS)
def test_point_near_wall_matches_form_factor(sampler):
    """A point on a large floor at distance h from a large wall (both, and the AO distance,
    much larger than h): AO = 1 - form factor to the wall rectangle, which tends to 0.5."""
    h, half_width, height = 0.02, 20.0, 20.0
    floor = np.array([[-50, -50, 0], [50, -50, 0], [50, 50, 0], [-50, 50, 0]], float)
    wall = np.array([[0, -half_width, 0], [0, half_width, 0], [0, half_width, height],
                     [0, -half_width, height]], float)
    vertices = np.concatenate([floor, wall]).astype(np.float32)
    indices = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]], np.int32)
    bvh = kernels.build_bvh(vertices, indices)
    r = 256
    y = np.linspace(-0.5, 0.5, r)
    target = np.c_[np.full(r, h), y, np.zeros(r)]
    origins = target + np.array([1.0, 0.0, 3.0])
    directions = target - origins
    spp = 256
    res = kernels.render_ao(bvh, origins.astype(np.float32), directions.astype(np.float32),
                            spp=spp, distance=1e3, seed=3, sampler=sampler)
    expected = np.array([1.0 - wall_form_factor(t, wall) for t in target])
    assert abs(expected.mean() - 0.5) < 0.005  # the form factor's limit, 0.5, within 0.005
    # Independent Bernoulli samples bound the standard error (Sobol's is smaller).
    se = np.sqrt(np.sum(expected * (1 - expected) / spp)) / r
    assert abs(res.ao.mean() - expected.mean()) < 4 * se
    assert np.all(np.abs(res.ao - expected) < 5 * np.sqrt(0.25 / spp))


def test_inside_closed_sphere_is_zero():
    """Inside a closed sphere with distance > diameter every occlusion ray hits: AO = 0."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    vertices = np.asarray(sphere.vertices, np.float32)
    bvh = kernels.build_bvh(vertices, np.asarray(sphere.faces, np.int32))
    rng = np.random.default_rng(5)
    d = rng.normal(size=(300, 3)).astype(np.float32)
    o = np.tile(np.float32([0.1, 0.2, -0.1]), (300, 1))
    for sampler in SAMPLERS:
        res = kernels.render_ao(bvh, o, d, spp=64, distance=2.5, sampler=sampler)
        assert np.all(res.spp_used == 64)
        assert np.all(res.ao == 0.0), f"{int((res.ao > 0).sum())} pixels saw out"


# --- a real scene against an independent reference ---------------------------------------


_PER_DEVICE: dict = {}  # (what, device) -> made once per test session


@pytest.fixture
def sponza(shared_scene, device):
    if ("sponza", device) not in _PER_DEVICE:
        scene = shared_scene("sponza")
        bvh = kernels.build_bvh(scene.vertices, scene.indices, device=device)
        cam = Camera.look_at((-13.0, 2.5, 0.0), (10.0, 4.5, 0.0), (0, 1, 0), 60.0, 40, 30)
        o, d, _, _ = cam.rays()
        _PER_DEVICE["sponza", device] = scene, bvh, o, d
    return _PER_DEVICE["sponza", device]


@pytest.fixture
def sponza_reference(sponza, device):
    """Our own AO at 2048 Sobol samples per pixel, a seed no other test uses."""
    if ("reference", device) not in _PER_DEVICE:
        _, bvh, o, d = sponza
        _PER_DEVICE["reference", device] = kernels.ambient_occlusion(bvh, o, d, spp=2048,
                                                                     seed=999)
    return _PER_DEVICE["reference", device]


def embree_ao(vertices, indices, o, d, spp, distance, seed):
    """AO written from the definition with Embree: closest hit, geometric normal facing
    the ray, a plain epsilon offset, independent uniform cosine-weighted directions."""
    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene, vertices, indices)
    res = scene.run(o, d, output=1)
    tri = res["primID"].astype(np.int64)
    hit = np.flatnonzero(tri >= 0)
    v = vertices.astype(np.float64)
    f = indices[tri[hit]]
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n *= -np.sign(np.einsum("ij,ij->i", n, d[hit]))[:, None]
    p = o[hit] + res["tfar"][hit, None].astype(np.float64) * d[hit]
    p += 1e-4 * n
    rng = np.random.default_rng(seed)
    u1, u2 = rng.random((2, len(hit), spp))
    r, phi = np.sqrt(u1), 2 * np.pi * u2
    local = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1 - u1)], -1)
    helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    w = local[..., :1] * t1[:, None] + local[..., 1:2] * t2[:, None] + local[..., 2:] * n[:, None]
    origins = np.repeat(p, spp, axis=0).astype(np.float32)
    dirs = w.reshape(-1, 3).astype(np.float32)
    occluded = scene.run(origins, dirs, dists=np.full(len(dirs), distance, np.float32),
                         query="OCCLUDED")
    ao = np.ones(len(o))
    ao[hit] = (occluded.reshape(-1, spp) != 0).mean(axis=1)
    return ao, tri


@pytest.mark.parametrize("sampler", SAMPLERS)
def test_unbiased_against_embree(sponza, sampler):
    scene, bvh, o, d = sponza
    spp, distance = 128, 3.0
    ours = kernels.render_ao(bvh, o, d, spp=spp, distance=distance, seed=11, sampler=sampler)
    ref, tri = embree_ao(scene.vertices, scene.indices, o, d, spp, distance, seed=12)
    ours_tri = kernels.trace(bvh, o, d).triangle
    both = (tri >= 0) & (tri == ours_tri)
    assert both.mean() > 0.95
    a, b = ours.ao[both].astype(np.float64), ref[both]
    # Standard error of the mean difference from both estimators' Bernoulli variances.
    se = np.sqrt(np.sum(a * (1 - a) / spp + b * (1 - b) / spp)) / both.sum()
    assert abs(a.mean() - b.mean()) < 3 * se, f"mean {a.mean():.4f} vs {b.mean():.4f}"
    assert np.array_equal(ours.ao[~(ours_tri >= 0)], np.ones(int((ours_tri < 0).sum())))


def rmse_slope(bvh, o, d, ref, sampler):
    spps = np.array([2, 4, 8, 16, 32, 64])
    err = [np.sqrt(np.mean((kernels.ambient_occlusion(bvh, o, d, spp=int(s), seed=21,
                                                      sampler=sampler) - ref) ** 2))
           for s in spps]
    return np.polyfit(np.log(spps), np.log(err), 1)[0], np.array(err)


def test_rmse_falls_as_inverse_sqrt_spp(sponza, sponza_reference):
    """Independent samples: RMSE ~ spp^-0.5. Owen-scrambled Sobol falls at least as fast
    and is below random at every spp from 4 up (the reason it is the default)."""
    _, bvh, o, d = sponza
    slope, err_random = rmse_slope(bvh, o, d, sponza_reference, "random")
    assert -0.6 <= slope <= -0.4, slope
    slope_sobol, err_sobol = rmse_slope(bvh, o, d, sponza_reference, "sobol")
    assert slope_sobol <= -0.45, slope_sobol
    assert np.all(err_sobol[1:] < err_random[1:]), (err_sobol, err_random)


def test_max_pixel_error_is_met(sponza, sponza_reference):
    """Per-pixel error against the 2048-spp reference is within max_pixel_error for >= 95%
    of pixels, and converged pixels stopped early (spp varies)."""
    _, bvh, o, d = sponza
    target = 0.05
    res = kernels.render_ao(bvh, o, d, max_pixel_error=target, seed=5, sampler="random")
    hit = res.spp_used > 0
    within = np.abs(res.ao - sponza_reference)[hit] <= target
    assert within.mean() >= 0.95, within.mean()
    assert res.spp_used[hit].min() >= 16
    assert res.spp_used[hit].min() < res.spp_used[hit].max() <= 1024
    res_sobol = kernels.render_ao(bvh, o, d, max_pixel_error=target, seed=5)
    assert (np.abs(res_sobol.ao - sponza_reference)[hit] <= target).mean() >= 0.95


def test_half_width_is_the_sample_variance_interval():
    """Disagreeing samples: z * sqrt(efficiency * s^2 / n) with the unbiased sample
    variance. Agreeing samples never give 0: the Jeffreys posterior mean stands in."""
    n = np.array([16, 100, 16, 16, 64])
    k = np.array([8, 50, 16, 0, 64])
    half = half_width(k, n, 1.0)
    assert abs(half[0] - Z95 * np.sqrt(0.25 * 16 / 15 / 16)) < 1e-12
    assert abs(half[1] - Z95 * np.sqrt(0.25 * 100 / 99 / 100)) < 1e-12
    q = 0.5 / 17
    assert abs(half[2] - half[3]) < 1e-15 and abs(half[2] - Z95 * np.sqrt(q * (1 - q) / 16)) < 1e-12
    assert 0 < half[4] < half[2] / 3  # ~1/n, not 1/sqrt(n)
    assert np.allclose(half_width(k, n, 0.25), half / 2)


def test_sampler_efficiency_of_independent_and_perfect_samples():
    """Independent samples measure as efficiency ~1; halves that agree exactly with the
    whole (a perfectly stratified sampler) as the floor; too few pixels: 1."""
    rng = np.random.default_rng(8)
    p = rng.uniform(0.1, 0.9, 4000)
    mid = rng.binomial(32, p)
    end = mid + rng.binomial(32, p)
    n_mid, n_end = np.full(4000, 32), np.full(4000, 64)
    assert sampler_efficiency(mid, n_mid, end, n_end) > 0.9
    assert sampler_efficiency(mid, n_mid, 2 * mid, n_end) == EFFICIENCY_MIN
    assert sampler_efficiency(mid[:10], n_mid[:10], end[:10], n_end[:10]) == 1.0


# --- skipping, determinism, progress, bad input ------------------------------------------


def test_adaptive_open_plane_stops_at_the_first_power_of_two_within_target():
    """Open-plane pixels agree on every sample: they double from the minimum spp until the
    half-width of agreeing samples is below the target, far below max_spp; rays that miss
    the scene box are never traced."""
    v, f = grid_plane(2)
    bvh = kernels.build_bvh(v.astype(np.float32), f)
    r = 200
    rng = np.random.default_rng(2)
    o = np.c_[rng.uniform(-0.9, 0.9, (r, 2)), np.ones(r)].astype(np.float32)
    d = np.tile(np.float32([0, 0, -1]), (r, 1))
    d[r // 2 :] *= -1  # pointing away from the plane's box: skipped
    res = kernels.render_ao(bvh, o, d, max_pixel_error=0.05, max_spp=1024)
    assert res.rays.primary == r // 2
    assert np.all(res.ao == 1.0)
    assert np.all(res.spp_used[r // 2 :] == 0)
    used = res.spp_used[: r // 2]
    assert np.all(used == 32)  # 16 (the default minimum) doubled once
    assert half_width(used // 2, used // 2, 1.0)[0] >= 0.05 > half_width(used, used, 1.0)[0]
    assert res.rays.occlusion == int(used.sum()) and res.rays.rounds == 2


def test_deterministic_for_any_thread_count(shared_scene):
    scene = shared_scene("sponza")
    bvh = kernels.build_bvh(scene.vertices, scene.indices)
    cam = Camera.look_at((-13.0, 2.5, 0.0), (10.0, 4.5, 0.0), (0, 1, 0), 60.0, 96, 96)
    o, d, tmin, tmax = cam.rays()
    one = kernels.render_ao(bvh, o, d, spp=3, seed=4, tmin=tmin, tmax=tmax, threads=1)
    assert one.rays.primary > 8192  # enough that two threads really split the work
    two = kernels.render_ao(bvh, o, d, spp=3, seed=4, tmin=tmin, tmax=tmax, threads=2)
    assert np.array_equal(one.ao, two.ao) and np.array_equal(one.spp_used, two.spp_used)
    other = kernels.ambient_occlusion(bvh, o, d, spp=3, seed=5, tmin=tmin, tmax=tmax)
    assert not np.array_equal(one.ao, other)


@pytest.mark.parametrize("target_error", [None, 0.05])
def test_dacrt_engine_gives_the_bvh_answer(shared_scene, target_error):
    """engine="dacrt" traces the same primary and occlusion rays without the BVH: the hit
    decisions agree, so the AO and the samples per pixel are identical."""
    scene = shared_scene("sibenik")
    bvh = kernels.build_bvh(scene.vertices, scene.indices)
    cam = Camera.look_at((-15.0, -5.0, 0.0), (-14.0, -5.2, 0.0), (0, 1, 0), 60.0, 40, 30)
    o, d, tmin, tmax = cam.rays()
    kw = {"spp": 8, "seed": 2, "tmin": tmin, "tmax": tmax, "target_error": target_error,
          "max_spp": 64}
    with_bvh = kernels.render_ao(bvh, o, d, **kw)
    with_dacrt = kernels.render_ao(bvh, o, d, engine="dacrt", **kw)
    assert with_bvh.rays.occlusion > 0
    assert np.array_equal(with_bvh.ao, with_dacrt.ao)
    assert np.array_equal(with_bvh.spp_used, with_dacrt.spp_used)


def test_progress_reports_and_cancels():
    v, f = grid_plane(2)
    bvh = kernels.build_bvh(v.astype(np.float32), f)
    o = np.tile(np.float32([0, 0, 1]), (10, 1))
    d = np.tile(np.float32([0, 0, -1]), (10, 1))
    seen: list[tuple[float, str]] = []
    kernels.render_ao(bvh, o, d, spp=4, progress=lambda x, phase: seen.append((x, phase)))
    fractions = [x for x, _ in seen]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    assert {"primary", "occlusion", "done"} <= {p for _, p in seen}

    def cancel(fraction: float, phase: str) -> None:
        if phase == "occlusion":
            raise KeyboardInterrupt("cancelled")

    with pytest.raises(KeyboardInterrupt):
        kernels.render_ao(bvh, o, d, spp=4, progress=cancel)


def test_adaptive_rounds_report_between_runs(monkeypatch):
    """An adaptive round larger than ROUND_RAYS is traced in runs with a progress call
    before each (Esc is seen there): a first round of 2M pixels at 16 samples is 32M rays.
    A cancel at the second call stops the render before the first round's second run."""
    from scenesort.kernels.render import adaptive

    monkeypatch.setattr(adaptive, "ROUND_RAYS", 4096)
    traced: list[int] = []
    real = adaptive.SampleCounts.trace

    def counting(self, trace_round, select, count):
        traced.append(len(select) * count)
        real(self, trace_round, select, count)

    monkeypatch.setattr(adaptive.SampleCounts, "trace", counting)
    v, f = grid_plane(4)
    bvh = kernels.build_bvh(v.astype(np.float32), f)
    rng = np.random.default_rng(2)
    n = 3000
    o = np.column_stack([rng.random((n, 2)) * 2 - 1, np.ones(n)]).astype(np.float32)
    d = np.tile(np.float32([0, 0, -1]), (n, 1))
    calls: list[int] = []

    def cancel_second(fraction: float, phase: str) -> None:
        if phase == "occlusion":
            calls.append(len(traced))
            if len(calls) == 2:
                raise KeyboardInterrupt("cancelled")

    with pytest.raises(KeyboardInterrupt):
        kernels.render_ao(bvh, o, d, spp=16, target_error=0.01, progress=cancel_second)
    assert calls == [0, 1] and traced[0] <= 2 * 4096 and traced[0] < n * 16


@pytest.mark.parametrize(
    "kwargs,field",
    [({"spp": 0}, "spp"), ({"distance": 0.0}, "distance"), ({"target_error": 1.5}, "target_error"),
     ({"max_pixel_error": 0.0}, "max_pixel_error"), ({"sampler": "halton"}, "sampler"),
     ({"target_error": 0.1, "spp": 64, "max_spp": 32},
                                          "max_spp"), ({"seed": 1.5}, "seed"),
     ({"engine": "optix"}, "engine")],
)
def test_bad_arguments_name_the_field(kwargs, field):
    v, f = grid_plane(1)
    bvh = kernels.build_bvh(v.astype(np.float32), f)
    o = np.float32([[0, 0, 1]])
    d = np.float32([[0, 0, -1]])
    with pytest.raises(ValueError, match=field):
        kernels.ambient_occlusion(bvh, o, d, **kwargs)


def test_compile_time_is_reported_apart(monkeypatch, device):
    """Warp's compile time (loading the render's modules first) is its own entry of
    `timings_ms`, not part of the render's total."""
    from scenesort.kernels.render import ao as ao_module

    monkeypatch.setattr(ao_module, "load_modules", lambda device, *modules: 1.0e6)
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    bvh = kernels.build_bvh(v, np.array([[0, 1, 2]], np.int32), device=device)
    result = kernels.render_ao(bvh, np.array([[0.2, 0.2, 1.0]], np.float32),
                               np.array([[0.0, 0.0, -1.0]], np.float32), spp=2)
    assert result.timings_ms.compile == 1.0e6 and result.timings_ms.total < 1.0e5


def test_progress_of_a_tiny_target_is_a_fraction():
    """The round loop's progress for any target in (0, 1): its aim squared underflows to 0
    for 1e-200 (the service answered 500 with a ZeroDivisionError there)."""
    from scenesort.kernels.render.adaptive import error_progress

    assert 0.0 < error_progress(1e-3, 5e-4, 1e-200) < 1.0
    assert error_progress(1e-3, 2e-3, 1e-200) == 0.0  # the error has not come down yet
    assert error_progress(1e-3, 1e-6, 0.01) == 1.0  # below the aim: done
    assert 0.0 < error_progress(1e-3, 5e-4, 0.01) < 1.0


def _touches_box(lo, hi, o, d, t0, t1) -> np.ndarray:
    """Oracle: the slab test in numpy float64, ray by ray through the axes."""
    out = np.zeros(len(o), dtype=bool)
    for i in range(len(o)):
        enter, leave, inside = float(t0[i]), float(t1[i]), True
        for k in range(3):
            ok, dk = float(o[i, k]), float(d[i, k])
            if dk == 0.0:
                inside &= lo[k] <= ok <= hi[k]
            else:
                a, b = (lo[k] - ok) / dk, (hi[k] - ok) / dk
                enter, leave = max(enter, min(a, b)), min(leave, max(a, b))
        out[i] = inside and enter <= leave
    return out


def test_box_candidates_are_the_rays_whose_segment_touches_the_widened_box():
    import warp as wp
    from scenesort.kernels.render.primary import box_candidates

    rng = np.random.default_rng(5)
    n = 4000
    o = rng.uniform(-3, 3, (n, 3)).astype(np.float32)
    d = (rng.uniform(-1.5, 1.5, (n, 3)) - o).astype(np.float32)  # toward the box
    d[rng.random((n, 3)) < 0.2] = 0.0  # rays in the slabs' planes, along axes
    d[np.all(d == 0, axis=1), 0] = 1.0
    o[:50] = np.round(o[:50])  # origins on the box's faces (lo -1, hi 1)
    t0 = rng.uniform(0.0, 1.0, n).astype(np.float32)
    t1 = np.where(rng.random(n) < 0.3, np.inf, t0 + rng.uniform(0, 4, n)).astype(np.float32)
    bounds = np.array([[-1, -1, -1], [1, 1, 1]], np.float32)
    arrays = [wp.array(x, dtype=dt, device="cpu")
              for x, dt in ((o, wp.vec3), (d, wp.vec3), (t0, float), (t1, float))]
    got = box_candidates(bounds, *arrays, threads=2)
    pad = 1e-5 * 3.0 + 1e-30
    want = np.flatnonzero(_touches_box(np.full(3, -1.0 - pad), np.full(3, 1.0 + pad),
                                       o.astype(np.float64),
                                       d.astype(np.float64), t0, t1))
    assert 0.2 * n < len(want) < 0.8 * n  # both answers are well represented
    np.testing.assert_array_equal(got, want)
    empty = np.array([[np.inf] * 3, [-np.inf] * 3], np.float32)
    assert len(box_candidates(empty, *arrays, threads=2)) == 0


def test_allocation_key_orders_under_first_then_by_gain():
    gain = np.array([1e-3, 1e-5, 1e-1, 2e-3, 1e-3], dtype=np.float32)
    under = np.array([False, True, False, True, False])
    order = np.argsort(allocation_key(gain, under), kind="stable")
    np.testing.assert_array_equal(order, [3, 1, 2, 0, 4])  # ties (0, 4) in item order
