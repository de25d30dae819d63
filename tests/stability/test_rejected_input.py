"""Rejected input: NaN/Inf anywhere, indices out of range, zero-length directions and
empty ranges are refused with a ValueError naming the problem (Python API) or a 4xx
(service), never a crash and never a silent wrong answer. test_trace.py covers the basic
ray cases; these add the mesh, float64 overflow, per-ray ranges, AO and the service."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from scenesort import kernels
from tests.backend.service_client import Api, ray_body, scene_body

from .cases import plane_grid

V, F = plane_grid(2)


def _with(a: np.ndarray, row: int, value) -> np.ndarray:
    a = np.array(a, copy=True)
    a[row] = value
    return a


@pytest.mark.parametrize(
    ("vertices", "indices", "message"),
    [
        (_with(V, 3, [np.nan, 0, 0]), F, "NaN or Inf"),
        (_with(V, 0, [0, np.inf, 0]), F, "NaN or Inf"),
        (_with(V, 8, [0, 0, -np.inf]), F, "NaN or Inf"),
        # Finite in float64 but not in float32: must not become a silent inf vertex.
        (_with(V.astype(np.float64), 2, [1e39, 0, 0]), F, "beyond the float32 range"),
        (V, _with(F, 1, [0, 1, len(V)]), "indices must lie in"),
        (V, _with(F, 0, [-1, 1, 2]), "indices must lie in"),
        (V, _with(F, 0, [0, 1, 2**31 - 1]), "indices must lie in"),
        (V, F.astype(np.float32), "int32"),
        (V.astype(np.int32), F, "float32"),
        (V[:, :2], F, "shape"),
        (V, F[:, :2], "shape"),
    ],
    ids=["nan", "inf", "-inf", "f64-overflow", "index=N", "index<0", "index-huge",
         "float-indices", "int-vertices", "2d-vertices", "pairs"],
)
def test_bad_meshes_are_rejected(vertices, indices, message):
    """Guards build_bvh against input that would read out of bounds or put NaN into
    boxes (a NaN box is entered by no ray or by every ray, silently)."""
    with pytest.raises(ValueError, match=message):
        kernels.build_bvh(vertices, indices)


@functools.cache
def _bvh() -> kernels.Bvh:
    return kernels.build_bvh(V, F)


ORIGINS = np.tile(np.array([[0.1, 1.0, 0.2]], np.float32), (6, 1))
DIRS = np.tile(np.array([[0.0, -1.0, 0.0]], np.float32), (6, 1))


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"origins": _with(ORIGINS, 5, [0, -np.inf, 0])}, "origins contains NaN or Inf in 1 rows"),
        ({"directions": _with(DIRS, 4, [np.nan, -1, 0])}, "directions contains NaN or Inf"),
        ({"origins": _with(ORIGINS.astype(np.float64), 1, [3e38 * 10, 0, 0])},
         "beyond the float32 range"),
        ({"directions": _with(DIRS, 2, [-0.0, 0.0, -0.0])}, "zero-length rows .first: row 2"),
        ({"tmax": np.array([1, 1, 1, 0.5, 1, 1], np.float32),
          "tmin": np.array([0, 0, 0, 0.6, 0, 0], np.float32)}, "tmax must be >= tmin"),
        ({"tmax": np.array([1, 1, 1, np.nan, 1, 1], np.float32)}, "tmax contains NaN"),
        ({"tmin": np.inf, "tmax": 1.0}, "tmax must be >= tmin"),
    ],
    ids=["-inf-origin", "nan-direction", "f64-overflow", "-0-direction", "range-one-ray",
         "nan-tmax", "inf-tmin"],
)
def test_bad_rays_are_rejected(kwargs, message):
    """Guards trace against rays that would give NaN t or a meaningless range; the
    message names the first bad row so the caller can find it."""
    args = {"origins": ORIGINS, "directions": DIRS, **kwargs}
    with pytest.raises(ValueError, match=message):
        kernels.trace(_bvh(), **args)


def test_infinite_but_valid_ranges_are_accepted():
    """Guards the other side: tmin = -inf, tmax = +inf and tmin == tmax are legal ranges,
    not errors; an empty-but-legal range [t, t] finds the hit only at exactly t."""
    h = kernels.trace(_bvh(), ORIGINS, DIRS, tmin=-np.inf, tmax=np.inf)
    assert np.all(h.t == 1.0)
    assert np.all(kernels.trace(_bvh(), ORIGINS, DIRS, tmin=1.0, tmax=1.0).t == 1.0)
    assert np.all(kernels.trace(_bvh(), ORIGINS, DIRS, tmin=0.5, tmax=0.5).triangle == -1)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"origins": _with(ORIGINS, 0, [np.nan, 0, 0])}, "NaN or Inf"),
        ({"directions": _with(DIRS, 3, [0, 0, 0])}, "zero-length"),
        ({"spp": 0}, "spp"),
        ({"distance": -1.0}, "distance"),
        ({"distance": float("nan")}, "distance"),
        ({"target_error": 1.5}, "target_error"),
    ],
    ids=["nan-origin", "zero-direction", "spp0", "negative-distance", "nan-distance",
         "target-error"],
)
def test_bad_ao_input_is_rejected(kwargs, message):
    """Guards ambient_occlusion: the same ray validation as trace, plus its own numbers
    (a NaN distance would silently turn every occlusion ray into a miss)."""
    args = {"origins": ORIGINS, "directions": DIRS, **kwargs}
    with pytest.raises(ValueError, match=message):
        kernels.ambient_occlusion(_bvh(), **args)


def _assert_4xx(response, field: str) -> None:
    assert 400 <= response.status_code < 500, (response.status_code, response.text[:300])
    assert field in response.text


@pytest.mark.host_only  # the HTTP layer, on the service's own device
def test_service_rejects_non_finite_and_out_of_range_input(api: Api):
    """Guards the HTTP path end to end: NaN/Inf vertices, out-of-range indices, NaN or
    zero-length rays and a body of the wrong size get a 4xx naming the problem (never a
    500 or a dropped connection), and the service still answers correctly afterwards."""
    bad_v = _with(V, 2, [np.nan, 0, 0])
    _assert_4xx(api.upload(bad_v, F), "finite")
    _assert_4xx(api.upload(_with(V, 1, [np.inf, 0, 0]), F), "finite")
    _assert_4xx(api.upload(V, _with(F, 0, [0, 1, len(V)])), "indices")
    _assert_4xx(api.upload(V, _with(F, 0, [-1, 1, 2])), "indices")
    ok = api.upload(V, F)
    assert ok.status_code in (200, 201), ok.text
    sid = ok.json()["scene_id"]
    _assert_4xx(api.ao(sid, _with(ORIGINS, 1, [np.nan, 1, 0]), DIRS), "finite")
    _assert_4xx(api.ao(sid, ORIGINS, _with(DIRS, 2, [0, np.inf, 0])), "finite")
    _assert_4xx(api.ao(sid, ORIGINS, _with(DIRS, 4, [0, 0, 0])), "direction")
    short = api.client.post(f"/v1/scenes/{sid}/ao", params={"rays": len(ORIGINS)},
                            content=ray_body(ORIGINS, DIRS)[:-4],
                            headers={"Content-Type": "application/octet-stream"})
    _assert_4xx(short, "body")
    raw = api.client.post("/v1/scenes", params={"vertices": len(V), "triangles": len(F)},
                          content=scene_body(V, F)[:-1],
                          headers={"Content-Type": "application/octet-stream"})
    _assert_4xx(raw, "body")
    # Still alive, and still right: AO of an open plane is exactly 1.
    assert api.health().status_code == 200
    good = api.ao(sid, ORIGINS, DIRS, spp=8)
    assert good.status_code == 200, good.text
    assert np.all(np.frombuffer(good.content, "<f4") == 1.0)
