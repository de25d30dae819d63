"""Denoising: the normal image, OIDN bringing a noisy render closer to
a converged reference, what the result claims, and the missing extra."""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest
from scenesort.backend.render.scenes import shared_scene
from scenesort.kernels.render.denoise import DenoiserMissing

from scenesort import kernels

WIDTH, HEIGHT = 128, 96
_CACHE: dict = {}


@pytest.fixture
def bunny(device):
    """The shared bunny at 128x96, its BVH and a 4096-spp reference (with its own MSE)."""
    if device not in _CACHE:
        scene = shared_scene("bunny", WIDTH, HEIGHT)
        o, d, tmin, tmax = scene.camera.rays()
        bvh = kernels.build_bvh(scene.vertices, scene.indices, device=device)
        kw = {"tmin": tmin, "tmax": tmax}
        ref = kernels.render_ao(bvh, o, d, spp=4096, seed=777, **kw)
        _CACHE[device] = scene, bvh, o, d, kw, ref
    return _CACHE[device]


def rmse(ao, ref) -> float:
    hit = ref.spp_used > 0
    mse = np.mean((ao[hit].astype(np.float64) - ref.ao[hit]) ** 2) - ref.rmse_estimate**2
    return math.sqrt(max(mse, 0.0))


def test_normals_are_the_hits_geometric_normals_facing_the_camera(bunny):
    """Without corner normals, `normals` is each hit triangle's unit normal turned toward
    the ray's origin (from the vertices in numpy), 0 where the ray missed."""
    scene, bvh, o, d, kw, _ = bunny
    res = kernels.render_ao(bvh, o, d, spp=1, **kw)
    hits = kernels.trace(bvh, o, d, kw["tmin"], kw["tmax"])
    hit = res.spp_used > 0
    np.testing.assert_array_equal(hit, hits.hit)
    assert np.all(res.normals[~hit] == 0.0)
    tri = scene.vertices[scene.indices[hits.triangle[hit]]].astype(np.float64)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n *= -np.sign(np.sum(n * d[hit], axis=1))[:, None]
    np.testing.assert_allclose(res.normals[hit], n, atol=1e-5)


@pytest.mark.parametrize(("spp", "bound"), [(2, 0.8), (4, 0.95)])
def test_denoised_image_is_closer_to_the_converged_reference(bunny, spp, bound):
    """At 2 and 4 spp OIDN's output is nearer the 4096-spp reference than the raw render:
    its RMSE below `bound` x the raw one (measured over seeds 0-4 at this size: 0.61-0.67x
    at 2 spp, 0.73-0.87x at 4, 0.88-0.93x at 8, where the bound would be too close to
    call); background pixels are untouched; the estimate and raw image are the raw
    render's."""
    _, bvh, o, d, kw, ref = bunny
    raw = kernels.render_ao(bvh, o, d, spp=spp, seed=3, **kw)
    den = kernels.render_ao(bvh, o, d, spp=spp, seed=3, denoise=True,
                            image_shape=(HEIGHT, WIDTH), **kw)
    assert den.denoised and den.stats().denoised and not raw.denoised
    np.testing.assert_array_equal(den.raw_ao, raw.ao)
    assert den.rmse_estimate == raw.rmse_estimate
    assert den.timings_ms.denoise is not None
    miss = raw.spp_used == 0
    np.testing.assert_array_equal(den.ao[miss], raw.ao[miss])
    assert den.ao.min() >= 0.0 and den.ao.max() <= 1.0
    assert rmse(den.ao, ref) < bound * rmse(raw.ao, ref), (rmse(den.ao, ref), rmse(raw.ao, ref))


def test_denoise_needs_the_image_shape(bunny):
    _, bvh, o, d, kw, _ = bunny
    with pytest.raises(ValueError, match="image_shape"):
        kernels.render_ao(bvh, o, d, spp=1, denoise=True, **kw)
    with pytest.raises(ValueError, match="image_shape"):
        kernels.render_ao(bvh, o, d, spp=1, denoise=True, image_shape=(WIDTH, WIDTH), **kw)


def test_a_missing_extra_names_it(bunny, monkeypatch):
    """Without pyoidn, denoise=True fails before tracing, naming the extra to install."""
    _, bvh, o, d, kw, _ = bunny
    monkeypatch.setitem(sys.modules, "pyoidn", None)  # import pyoidn raises ImportError
    with pytest.raises(DenoiserMissing, match=r'pip install "scenesort\[denoise\]"'):
        kernels.render_ao(bvh, o, d, spp=1, denoise=True, image_shape=(HEIGHT, WIDTH), **kw)
    assert kernels.render_ao(bvh, o, d, spp=1, **kw).denoised is False  # the rest works
