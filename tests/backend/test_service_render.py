"""Upload -> BVH -> AO over HTTP returns exactly what the direct kernel calls return."""

from __future__ import annotations

import numpy as np
import pytest

from scenesort import kernels


@pytest.fixture(scope="module")
def scene_id(api, box_scene) -> str:
    response = api.upload(*box_scene)
    assert response.status_code in (200, 201), response.text
    return response.json()["scene_id"]


@pytest.mark.parametrize(("method", "leaf_size"), [("sah", 8), ("median", 4)])
def test_bvh_over_http_matches_a_direct_build(api, box_scene, method, leaf_size):
    vertices = box_scene[0] * np.float32(2.0) + np.float32(leaf_size)  # no other test's scene
    scene = (vertices, box_scene[1])
    scene_id = api.upload(*scene).json()["scene_id"]
    spec = {"method": method, "leaf_size": leaf_size}
    first = api.client.post(f"/v1/scenes/{scene_id}/bvh", json=spec)
    assert first.status_code == 200, first.text
    info = first.json()
    direct = kernels.build_bvh(*scene, method=method, leaf_size=leaf_size, device="cpu")
    for key in ("nodes", "leaves", "depth", "triangles", "degenerate"):
        assert info["stats"][key] == getattr(direct.stats, key), key
    assert info["stats"]["sah_cost"] == pytest.approx(direct.stats.sah_cost, rel=1e-12)
    assert set(direct.stats.phase_ms) | {"total", "compile"} == set(info["timings_ms"])
    again = api.client.post(f"/v1/scenes/{scene_id}/bvh", json=spec).json()
    assert (info["cached"], again["cached"]) == (False, True)
    assert again["timings_ms"] == info["timings_ms"]  # the original build's, reused


@pytest.mark.parametrize(
    "params",
    [
        {"spp": 8, "seed": 3},
        {"spp": 4, "distance": 0.25, "seed": 0},
        {"spp": 16, "seed": 7, "target_error": 0.05, "method": "median", "leaf_size": 4},
    ],
    ids=["spp8", "distance", "target-error"],
)
def test_ao_over_http_equals_the_direct_call(api, box_scene, scene_id, make_rays, params):
    origins, directions = make_rays(300, seed=params["seed"] + 1)
    response = api.ao(scene_id, origins, directions, **params)
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "application/octet-stream"
    timing = response.headers["server-timing"]
    assert all(f"{name};dur=" in timing for name in ("decode", "ao", "total"))
    got = np.frombuffer(response.content, "<f4")
    engine_params = {k: v for k, v in params.items() if k not in ("method", "leaf_size")}
    bvh = kernels.build_bvh(
        *box_scene,
        method=params.get("method", "sah"),
        leaf_size=params.get("leaf_size", 8),
        device="cpu",
    )
    expected = kernels.ambient_occlusion(bvh, origins, directions, **engine_params)
    assert got.shape == (300,)
    np.testing.assert_array_equal(got, np.asarray(expected, np.float32))
    assert 0.0 < got.min() < 1.0 and got.max() == 1.0  # occluded floor and missed rays


def _smooth_normals(vertices: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """Corner normals of the scene's vertices pointing away from its centre (any smooth
    field will do: it makes the shading differ from the geometric one)."""
    v = vertices.astype(np.float64)[indices]
    out = v - vertices.astype(np.float64).mean(axis=0) + [0.0, 1.0, 0.0]
    return (out / np.linalg.norm(out, axis=2, keepdims=True)).astype(np.float32)


def test_normals_travel_with_the_scene(api, box_scene, make_rays):
    """A scene uploaded with normals (and per-triangle terminator offsets) renders as the
    direct call with them; its id is another scene's than the same triangles without."""
    vertices, indices = box_scene
    normals = _smooth_normals(vertices, indices)
    offsets = np.linspace(0.0, 0.5, len(indices)).astype(np.float32)
    plain = api.upload(vertices, indices).json()
    answer = api.upload(vertices, indices, normals, offsets)
    assert answer.status_code in (200, 201), answer.text
    info = answer.json()
    assert info["normals"] and not plain["normals"] and info["scene_id"] != plain["scene_id"]
    assert info["bytes"] == plain["bytes"] + 40 * len(indices)
    origins, directions = make_rays(300, seed=11)
    params = {"spp": 8, "seed": 2, "distance": 1.0}
    got = np.frombuffer(api.ao(info["scene_id"], origins, directions, **params).content, "<f4")
    flat = np.frombuffer(api.ao(plain["scene_id"], origins, directions, **params).content, "<f4")
    bvh = kernels.build_bvh(vertices, indices, device="cpu")
    expected = kernels.ambient_occlusion(bvh, origins, directions, normals=normals,
                                         terminator_offset=offsets, **params)
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(flat, kernels.ambient_occlusion(bvh, origins, directions,
                                                                  **params))
    assert not np.array_equal(got, flat)


@pytest.mark.parametrize(
    ("query", "extra", "status", "parameter"),
    [({"terminator_offsets": "true"}, 4, 422, "terminator_offsets"),
     ({"normals": "true"}, 0, 400, "body"),
     ({"normals": "true"}, 36 + 1, 400, "body")],
    ids=["offsets-without-normals", "normal-block-missing", "normal-block-too-long"],
)
def test_bad_shading_uploads_are_problems_naming_the_field(api, box_scene, query, extra,
                                                           status, parameter):
    vertices, indices = box_scene
    content = vertices.astype("<f4").tobytes() + indices.astype("<i4").tobytes()
    content += b"\0" * (extra * len(indices))
    response = api.client.post(
        "/v1/scenes", params={"vertices": len(vertices), "triangles": len(indices), **query},
        content=content, headers={"Content-Type": "application/octet-stream"})
    assert response.status_code == status, response.text
    problem = response.json()
    assert problem["parameter"] == parameter and problem["fix"], problem
