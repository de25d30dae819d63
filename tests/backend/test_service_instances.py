"""Meshes by content hash (HEAD/PUT /v1/meshes/{id}) and scenes as instance lists
(POST /v1/instance-scenes) on a real service, bad input included: every refusal is a 4xx
naming the field at fault, behind the same token, Content-Type and body checks."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import httpx
import numpy as np
import pytest
from scenesort.backend.render.bundle import instance_body, mesh_id
from scenesort.backend.wire import binary as wire
from service_client import OCTET, floor_and_box, job_ended, rays_towards_floor, scene_body


def cube() -> tuple[np.ndarray, np.ndarray]:
    """A closed unit cube centred on the origin (12 triangles)."""
    v = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)],
                 np.float32)
    f = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
         [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    return v, np.array(f, np.int32)


def put_mesh(api, vertices, indices, name: str | None = None, **params) -> httpx.Response:  # noqa: ANN001
    return api.client.put(
        f"/v1/meshes/{name or mesh_id(vertices, indices)}",
        params={"vertices": len(vertices), "triangles": len(indices), **params},
        content=scene_body(vertices, indices), headers=OCTET)


def post_instances(api, ids, mesh_index, transforms, **params) -> httpx.Response:  # noqa: ANN001
    query = {"meshes": len(ids), "instances": len(mesh_index), **params}
    return api.client.post("/v1/instance-scenes", params=query, headers=OCTET,
                           content=instance_body(ids, mesh_index, transforms))


def transforms(*offsets: tuple[float, float, float], scale: float = 1.0) -> np.ndarray:
    out = np.zeros((len(offsets), 3, 4), np.float32)
    out[:, :, :3] = scale * np.eye(3, dtype=np.float32)
    out[:, :, 3] = offsets
    return out


@pytest.fixture(scope="module")
def meshes(api) -> dict[str, str]:  # noqa: ANN001
    """The cube and the floor-and-box on the service, by name."""
    ids = {}
    for name, (v, i) in {"cube": cube(), "floor": floor_and_box()}.items():
        answer = put_mesh(api, v, i)
        assert answer.status_code in (200, 201), answer.text
        ids[name] = answer.json()["scene_id"]
    return ids


def test_mesh_put_is_201_then_200_and_head_finds_it(api) -> None:  # noqa: ANN001
    v, i = cube()
    v = v * 3.0  # a mesh no other test uploads
    name = mesh_id(v, i)
    assert api.client.head(f"/v1/meshes/{name}").status_code == 404
    first, again = put_mesh(api, v, i), put_mesh(api, v, i)
    assert (first.status_code, again.status_code) == (201, 200)
    assert first.json()["scene_id"] == name and first.json()["triangles"] == 12
    assert api.client.head(f"/v1/meshes/{name}").status_code == 200
    # a mesh is a single-mesh scene too
    assert api.client.get(f"/v1/scenes/{name}").json()["vertices"] == 8


def test_mesh_under_another_name_is_refused(api) -> None:  # noqa: ANN001
    v, i = cube()
    answer = put_mesh(api, v, i, name="0" * 32)
    assert answer.status_code == 422 and answer.json()["parameter"] == "mesh_id"
    assert mesh_id(v, i) in answer.json()["detail"]


@pytest.mark.parametrize(("change", "status", "parameter"), [
    ({"params": {"vertices": 9}}, 400, "body"),
    ({"params": {"triangles": 0}}, 422, "triangles"),
    ({"headers": {"Content-Type": "application/json"}}, 415, "Content-Type"),
    ({"headers": {"Authorization": "Bearer wrong"}}, 401, "Authorization"),
])
def test_bad_mesh_uploads_name_the_field(api, change, status, parameter) -> None:  # noqa: ANN001
    v, i = cube()
    params = {"vertices": len(v), "triangles": len(i), **change.get("params", {})}
    headers = {**OCTET, **change.get("headers", {})}
    answer = api.client.put(f"/v1/meshes/{mesh_id(v, i)}", params=params,
                            content=scene_body(v, i), headers=headers)
    assert answer.status_code == status and answer.json()["parameter"] == parameter
    assert answer.json()["fix"]


def test_instance_list_is_a_scene_with_its_world_box(api, meshes) -> None:  # noqa: ANN001
    ids = [meshes["cube"], meshes["floor"]]
    placed = transforms((0, 0, 0), (5, 0, 0), (0, 3, 0))
    placed[1, :, :3] = np.diag([-1.0, 2.0, 1.0])  # mirrored and stretched
    first = post_instances(api, ids, [0, 0, 1], placed)
    again = post_instances(api, ids, [0, 0, 1], placed)
    assert (first.status_code, again.status_code) == (201, 200)
    info = first.json()
    scene_id = info["scene_id"]
    body = instance_body(ids, [0, 0, 1], placed)
    assert scene_id == wire.instances_hash(2, 3, body)
    floor_v, floor_i = floor_and_box()
    assert info["meshes"] == ids and info["instances"] == 3
    assert info["triangles"] == 12 + 12 + len(floor_i)
    corners = [cube()[0] @ t[:, :3].T.astype(np.float64) + t[:, 3] for t in placed[:2]]
    corners.append(floor_v.astype(np.float64) + placed[2, :, 3])
    world = np.concatenate(corners)
    np.testing.assert_allclose(info["bounds"], [world.min(0), world.max(0)], atol=1e-6)
    assert api.client.head(f"/v1/scenes/{scene_id}").status_code == 200
    assert api.client.get(f"/v1/scenes/{scene_id}").json() == info


def test_an_instance_list_is_its_bytes(api, meshes) -> None:  # noqa: ANN001
    """Moving one instance is a new scene id; the same list again is the same id."""
    ids = [meshes["cube"]]
    a = post_instances(api, ids, [0, 0], transforms((0, 0, 0), (2, 0, 0))).json()["scene_id"]
    b = post_instances(api, ids, [0, 0], transforms((0, 0, 0), (2, 0, 1))).json()["scene_id"]
    assert a != b


def test_unknown_mesh_is_404_naming_the_mesh_ids(api, meshes) -> None:  # noqa: ANN001
    missing = "f" * 32
    answer = post_instances(api, [meshes["cube"], missing], [0, 1], transforms((0, 0, 0),
                                                                               (1, 1, 1)))
    assert answer.status_code == 404
    problem = answer.json()
    assert problem["parameter"] == "body (mesh ids)" and missing in problem["detail"]
    assert "PUT /v1/meshes" in problem["fix"]


def _bad_transforms(kind: str) -> np.ndarray:
    out = transforms((0, 0, 0), (1, 0, 0))
    if kind == "nan":
        out[1, 0, 3] = np.nan
    else:
        out[1, :, :3] = 0.0
    return out


@pytest.mark.parametrize(("ids", "index", "placed", "parameter", "words"), [
    (["CUBE" * 8], [0], transforms((0, 0, 0)), "body (mesh ids)", "hex"),
    (None, [0, 2], transforms((0, 0, 0), (1, 0, 0)), "body (mesh indices)", "instance 1"),
    (None, [0, 0], _bad_transforms("nan"), "body (transforms)", "instance 1"),
    (None, [0, 0], _bad_transforms("zero"), "body (transforms)", "singular"),
])
def test_bad_instance_lists_are_400_naming_the_part(api, meshes, ids, index, placed,  # noqa: ANN001
                                                    parameter, words) -> None:
    answer = post_instances(api, ids or [meshes["cube"]], index, placed)
    assert answer.status_code == 400, answer.text
    assert answer.json()["parameter"] == parameter and words in answer.json()["detail"]


def test_instance_list_length_and_counts_are_checked(api, meshes) -> None:  # noqa: ANN001
    body = instance_body([meshes["cube"]], [0], transforms((0, 0, 0)))
    short = api.client.post("/v1/instance-scenes", params={"meshes": 1, "instances": 1},
                            content=body[:-4], headers=OCTET)
    assert short.status_code == 400 and short.json()["parameter"] == "body"
    zero = api.client.post("/v1/instance-scenes", params={"meshes": 1, "instances": 0},
                           content=body, headers=OCTET)
    assert zero.status_code == 422 and zero.json()["parameter"] == "instances"
    untyped = api.client.post("/v1/instance-scenes", params={"meshes": 1, "instances": 1},
                              content=body)
    assert untyped.status_code == 415


def test_dacrt_is_refused_for_an_instance_list(api, meshes) -> None:  # noqa: ANN001
    scene_id = post_instances(api, [meshes["cube"]], [0], transforms((0, 0, -4))).json()
    camera = {"matrix_world": np.eye(4).tolist(), "width": 8, "height": 6}
    answer = api.client.post("/v1/jobs", json={"scene_id": scene_id["scene_id"],
                                               "camera": camera, "engine": "dacrt"})
    assert answer.status_code == 422 and answer.json()["parameter"] == "engine"


def test_decode_instances_keeps_the_values() -> None:
    """The decoded list is the body's values, native float32/int32 (no server)."""
    ids = ["a" * 32, "b" * 32]
    placed = transforms((1, 2, 3), (4, 5, 6), scale=2.0)
    listing = wire.decode_instances(instance_body(ids, [1, 0], placed), 2, 2)
    assert listing.mesh_ids == tuple(ids)
    np.testing.assert_array_equal(listing.mesh_index, [1, 0])
    np.testing.assert_array_equal(listing.transforms, placed)
    assert listing.transforms.dtype == np.float32 and listing.mesh_index.dtype == np.int32


def _job(api, scene_id: str, camera: dict, **fields) -> dict:  # noqa: ANN001, ANN003
    job = api.client.post("/v1/jobs", json={"scene_id": scene_id, "camera": camera, "spp": 4,
                                            "seed": 2, "distance": 0.5, **fields})
    assert job.status_code == 202, job.text
    status = job_ended(api.client, job.json()["job_id"])
    assert status["state"] == "done", status
    ao = api.client.get(f"/v1/jobs/{status['job_id']}/result", params={"format": "f32"})
    return {**status, "ao": np.frombuffer(ao.content, "<f4")}


def test_a_deformed_mesh_is_refit_and_renders_as_a_fresh_build(api) -> None:  # noqa: ANN001
    """A mesh of an instance list with an earlier one's positions moved (same topology) is
    refit from that one's BVH, and the image is a fresh build's; the same arrays through
    the single-mesh API are built afresh (its BVH statistics stay a build's)."""
    from scenesort.kernels import Camera

    from scenesort import kernels

    v, i = floor_and_box(6)
    moved = v.copy()
    moved[:, 1] += 0.05 * np.sin(3.0 * v[:, 0])  # same triangles, new positions
    camera = Camera.look_at((0.3, 2.0, 2.0), (0, 0, 0), (0, 1, 0), 50.0, 16, 12).to_dict()
    reports = []
    for positions in (v, moved):
        name = put_mesh(api, positions, i).json()["scene_id"]
        listing = post_instances(api, [name], [0], transforms((0, 0, 0))).json()
        reports.append(_job(api, listing["scene_id"], camera))
    assert reports[0]["build"]["built"] == [mesh_id(v, i)]
    assert reports[1]["build"]["refit"] == [mesh_id(moved, i)]
    assert not reports[1]["build"]["built"] and reports[1]["build"]["top_level"] == "built"
    o, d, tmin, tmax = Camera.from_dict(camera).rays()
    direct = kernels.render_ao(kernels.build_bvh(moved, i), o, d, spp=4, seed=2,
                               distance=0.5, tmin=tmin, tmax=tmax)
    np.testing.assert_array_equal(reports[1]["ao"], direct.ao)
    flat_moved = moved + np.float32(1.0)  # a single-mesh scene of the same topology
    flat = _job(api, api.upload(flat_moved, i).json()["scene_id"], camera)
    assert flat["build"]["built"] and flat["build"]["top_level"] == "none"


def test_varying_terminator_offsets_are_refused_in_an_instance_list(api) -> None:  # noqa: ANN001
    """An instance has one terminator offset (Blender's is per object): a mesh whose
    triangles carry different ones cannot be instanced, and the 422 says so."""
    v, i = cube()
    normals = np.tile(np.float32([0, 0, 1]), (len(i), 3, 1))
    offsets = np.linspace(0.0, 0.5, len(i), dtype=np.float32)
    body = scene_body(v, i) + normals.astype("<f4").tobytes() + offsets.astype("<f4").tobytes()
    name = wire.scene_hash(len(v), len(i), body)
    put = api.client.put(f"/v1/meshes/{name}", content=body, headers=OCTET, params={
        "vertices": len(v), "triangles": len(i), "normals": "true",
        "terminator_offsets": "true"})
    assert put.status_code == 201, put.text
    answer = post_instances(api, [name], [0], transforms((0, 0, 0)))
    assert answer.status_code == 422 and answer.json()["parameter"] == "body (mesh ids)"
    assert "terminator offsets" in answer.json()["detail"]


def test_ao_on_an_instance_list_is_the_flattened_scenes(api, meshes) -> None:  # noqa: ANN001
    """POST .../ao on an instance list gives the flattened triangles' AO, bit for bit (same
    rays and samples), and its BVH route says that jobs build its levels."""
    from service_client import rays_towards_floor

    from scenesort import kernels

    placed = transforms((0.0, 0.0, 0.0), (0.4, 0.3, -0.2))
    placed[1, :, :3] = np.diag([-0.5, 0.7, 0.5])  # mirrored, non-uniform
    scene_id = post_instances(api, [meshes["floor"], meshes["cube"]], [0, 1], placed)
    scene_id = scene_id.json()["scene_id"]
    o, d = rays_towards_floor(300, seed=4)
    answer = api.ao(scene_id, o, d, spp=8, seed=3, distance=0.5)
    assert answer.status_code == 200, answer.text
    (fv, fi), (cv, ci) = floor_and_box(), cube()
    world = cv.astype(np.float64) @ placed[1, :, :3].T.astype(np.float64) + placed[1, :, 3]
    vertices = np.concatenate([fv, world.astype(np.float32)])
    indices = np.concatenate([fi, ci[:, ::-1] + len(fv)])  # the mirror flips the winding
    direct = kernels.ambient_occlusion(kernels.build_bvh(vertices, indices), o, d, spp=8,
                                       seed=3, distance=0.5)
    np.testing.assert_array_equal(np.frombuffer(answer.content, "<f4"), direct)
    refused = api.client.post(f"/v1/scenes/{scene_id}/bvh", json={})
    assert refused.status_code == 422 and refused.json()["parameter"] == "scene_id"


@pytest.mark.parametrize("mirrored", [False, True])
def test_smooth_meshes_shade_as_their_flattened_triangles(api, mirrored) -> None:  # noqa: ANN001
    """Object-space corner normals of a mesh in an instance list (a rotated, stretched and,
    or not, mirrored instance; a terminator offset) shade as the flattened scene with
    world-space normals (the inverse transpose; a mirror reverses the winding and the
    corners, as addon/export.py flattens) does, bit for bit."""
    from scenesort import kernels

    v, i = floor_and_box(4)
    normals = (v[i] + np.float32([0.0, 0.5, 0.0]))  # smooth, pointing away from below
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    offsets = np.full(len(i), 0.3, np.float32)
    body = (scene_body(v, i) + normals.astype("<f4").tobytes()
            + offsets.astype("<f4").tobytes())
    name = wire.scene_hash(len(v), len(i), body)
    put = api.client.put(f"/v1/meshes/{name}", content=body, headers=OCTET, params={
        "vertices": len(v), "triangles": len(i), "normals": "true",
        "terminator_offsets": "true"})
    assert put.status_code in (200, 201), put.text
    c, s = np.cos(0.4), np.sin(0.4)
    placed = transforms((0.0, 0.0, 0.0), (0.3, 0.1, 0.2))
    stretch = np.diag([-0.6 if mirrored else 0.6, 0.4, 0.5])
    placed[1, :, :3] = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]) @ stretch
    listing = post_instances(api, [name], [0, 0], placed).json()["scene_id"]
    o, d = rays_towards_floor(400, seed=6)
    answer = api.ao(listing, o, d, spp=8, seed=5, distance=0.4)
    assert answer.status_code == 200, answer.text
    world_v, world_i, world_n = [], [], []
    for k, m in enumerate(placed.astype(np.float64)):
        world_v.append((v @ m[:, :3].T + m[:, 3]).astype(np.float32))
        n = normals.astype(np.float64) @ np.linalg.inv(m[:, :3])  # rows: (M^-T n)^T
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        flip = np.linalg.det(m[:, :3]) < 0
        world_i.append((i[:, ::-1] if flip else i) + k * len(v))
        world_n.append((n[:, ::-1] if flip else n).astype(np.float32))
    bvh = kernels.build_bvh(np.concatenate(world_v), np.concatenate(world_i))
    direct = kernels.ambient_occlusion(bvh, o, d, spp=8, seed=5, distance=0.4,
                                       normals=np.concatenate(world_n), terminator_offset=0.3)
    np.testing.assert_array_equal(np.frombuffer(answer.content, "<f4"), direct)


def post_masked(api, ids, mesh_index, placed, masks) -> httpx.Response:  # noqa: ANN001
    query = {"meshes": len(ids), "instances": len(mesh_index), "visibility": "true"}
    return api.client.post("/v1/instance-scenes", params=query, headers=OCTET,
                           content=instance_body(ids, mesh_index, placed, masks))


def test_visibility_masks_are_counted_and_checked(api, meshes) -> None:  # noqa: ANN001
    ids = [meshes["floor"], meshes["cube"]]
    placed = transforms((0, 0, 0), (0.3, 0.2, 0.0), (-0.3, 0.2, 0.0))
    masks = [wire.CAMERA | wire.SHADOW, wire.SHADOW, wire.CAMERA | wire.HOLDOUT]
    answer = post_masked(api, ids, [0, 1, 1], placed, masks)
    assert answer.status_code == 201, answer.text
    assert answer.json()["visibility"] == {"camera": 2, "shadow": 2, "holdout": 1}
    plain = post_instances(api, ids, [0, 1, 1], placed).json()
    assert plain["visibility"] == {"camera": 3, "shadow": 3, "holdout": 0}
    assert plain["scene_id"] != answer.json()["scene_id"]
    bad = post_masked(api, ids, [0, 1, 1], placed, [3, 3, 9])
    assert bad.status_code == 400 and bad.json()["parameter"] == "body (visibility masks)"
    assert "instance 2" in bad.json()["detail"]
    short = api.client.post("/v1/instance-scenes", headers=OCTET, params={
        "meshes": 2, "instances": 3, "visibility": "true"},
        content=instance_body(ids, [0, 1, 1], placed))  # the masks left out
    assert short.status_code == 400 and "223 bytes" in short.json()["detail"]  # 32*2 + 53*3


def _masked_scene(api, meshes) -> tuple[str, dict, Callable[..., Any]]:  # noqa: ANN001
    """A floor seen and occluding, a cube that only occludes and one that is a holdout, as
    a list with masks: its id, a camera on them, and scene(*keep) the engine's Scene of the
    instances `keep` over the same meshes."""
    from scenesort.kernels import Camera

    from scenesort import kernels

    ids = [meshes["floor"], meshes["cube"]]
    placed = transforms((0, 0, 0), (0.3, 0.0, 0.3), (-0.3, 0.0, 0.3), scale=0.5)
    placed[0, :, :3] = np.eye(3)
    masks = np.array([wire.CAMERA | wire.SHADOW, wire.SHADOW, wire.CAMERA | wire.HOLDOUT
                      | wire.SHADOW], np.uint8)
    scene_id = post_masked(api, ids, [0, 1, 1], placed, masks).json()["scene_id"]
    camera = Camera.look_at((0.0, 2.0, 2.0), (0, 0, 0), (0, 1, 0), 50.0, 24, 18).to_dict()
    (fv, fi), (cv, ci) = floor_and_box(), cube()
    bvhs = [kernels.build_bvh(fv, fi), kernels.build_bvh(cv, ci)]

    def scene(*keep: int) -> Any:
        return kernels.build_scene(bvhs, [0, 1, 1], placed, visible=np.isin(range(3), keep))

    return scene_id, camera, scene


def test_a_job_honours_visibility_masks(api, meshes) -> None:  # noqa: ANN001
    """A job over a list with masks renders as kernels.render_ao with the camera's, the
    occluders' and the holdout's instances (bit for bit), reports the holdout pixels and
    their depth, and a second job builds nothing."""
    from scenesort.kernels import Camera

    from scenesort import kernels

    scene_id, camera, scene = _masked_scene(api, meshes)
    first = _job(api, scene_id, camera)
    again = _job(api, scene_id, camera)
    assert first["build"]["top_level"] == "built" and again["build"]["top_level"] == "reused"
    np.testing.assert_array_equal(first["ao"], again["ao"])

    o, d, tmin, tmax = Camera.from_dict(camera).rays()
    direct = kernels.render_ao(scene(0), o, d, spp=4, seed=2, distance=0.5, tmin=tmin,
                               tmax=tmax, occluders=scene(0, 1, 2), holdout=scene(2))
    np.testing.assert_array_equal(first["ao"], direct.ao)
    held = api.client.get(f"/v1/jobs/{first['job_id']}/result", params={"format": "holdout"})
    held = np.frombuffer(held.content, "<f4")
    np.testing.assert_array_equal(held, direct.holdout.astype(np.float32))
    assert 0 < held.sum() < len(held)
    coverage = api.client.get(f"/v1/jobs/{first['job_id']}/result",
                              params={"format": "coverage"})
    assert not np.frombuffer(coverage.content, "<f4")[held > 0].any()
    depth = api.client.get(f"/v1/jobs/{first['job_id']}/result", params={"format": "depth"})
    assert (np.frombuffer(depth.content, "<f4")[held > 0] < 1e9).all()  # the holdout's


def test_a_filtered_job_holds_out_sample_by_sample(api, meshes) -> None:  # noqa: ANN001
    """Through Cycles' pixel filter a holdout is a fraction of each pixel's samples: the
    job's AO, coverage, holdout and normal layers are kernels.render_film's with the
    camera's, the occluders' and the holdout's instances, bit for bit, and its film is the
    filter's (the Normal pass rendered through it too)."""
    from scenesort.kernels import Camera

    from scenesort import kernels

    scene_id, camera, scene = _masked_scene(api, meshes)
    film = {"pixel_filter": "BLACKMAN_HARRIS", "filter_width": 1.5}
    job = _job(api, scene_id, camera, passes=["normal"], **film)
    assert job["film"] == "BLACKMAN_HARRIS 1.5 px", job["film"]

    def layer(name: str) -> np.ndarray:
        got = api.client.get(f"/v1/jobs/{job['job_id']}/result", params={"format": name})
        return np.frombuffer(got.content, "<f4")

    direct = kernels.render_film(scene(0), Camera.from_dict(camera), spp=4, seed=2,
                                 distance=0.5, occluders=scene(0, 1, 2), holdout=scene(2),
                                 **film)
    np.testing.assert_array_equal(job["ao"], direct.ao.ravel())
    np.testing.assert_array_equal(layer("coverage"), direct.alpha.ravel())
    held = layer("holdout")
    np.testing.assert_array_equal(held, direct.holdout.ravel())
    assert ((held > 0) & (held < 1)).any() and (held == 1).any()  # edges and whole pixels
    np.testing.assert_array_equal(layer("normal"), direct.normals.ravel())


def test_extra_passes_are_kept_when_asked_for(api, meshes) -> None:  # noqa: ANN001
    """A job's passes: the shading normals render_ao found, the hit points (on the
    instances' world triangles), the instance each camera ray hit (-1 on background)
    and the triangle in its mesh (two halves; -1, -1 on background);
    a pass not asked for is a 409 naming `format`."""
    from scenesort.kernels import Camera

    from scenesort import kernels

    ids = [meshes["floor"], meshes["cube"]]
    placed = transforms((0, 0, 0), (0.3, 0.0, 0.3), scale=0.5)
    placed[0, :, :3] = np.eye(3)
    scene_id = post_instances(api, ids, [0, 1], placed).json()["scene_id"]
    camera = Camera.look_at((0.0, 2.0, 2.0), (0, 0, 0), (0, 1, 0), 50.0, 24, 18).to_dict()
    job = api.client.post("/v1/jobs", json={"scene_id": scene_id, "camera": camera, "spp": 4,
                                            "seed": 2, "distance": 0.5,
                                            "passes": ["normal", "position", "object",
                                                       "triangle"]})
    assert job.status_code == 202, job.text
    status = job_ended(api.client, job.json()["job_id"])

    def layer(name: str, channels: int = 1) -> np.ndarray:
        got = api.client.get(f"/v1/jobs/{status['job_id']}/result", params={"format": name})
        assert got.status_code == 200, got.text
        return np.frombuffer(got.content, "<f4").reshape(-1, channels)

    (fv, fi), (cv, ci) = floor_and_box(), cube()
    scene = kernels.build_scene([kernels.build_bvh(fv, fi), kernels.build_bvh(cv, ci)],
                                [0, 1], placed)
    o, d, tmin, tmax = Camera.from_dict(camera).rays()
    direct = kernels.render_ao(scene, o, d, spp=4, seed=2, distance=0.5, tmin=tmin, tmax=tmax)
    hits = kernels.trace(scene, o, d, tmin, tmax)
    np.testing.assert_array_equal(layer("normal", 3), direct.normals)
    np.testing.assert_array_equal(layer("object")[:, 0], np.where(hits.hit, hits.instance, -1))
    assert {0, 1} <= set(hits.instance.tolist())
    halves = layer("triangle", 2).astype(np.int64)
    np.testing.assert_array_equal(halves[:, 0] * 65536 + halves[:, 1],
                                  np.where(hits.hit, hits.triangle, -65537))
    assert len(set(hits.triangle[hits.hit].tolist())) > 4
    expected = np.where(hits.hit[:, None], o + hits.t[:, None].astype(np.float64) * d, 0.0)
    np.testing.assert_allclose(layer("position", 3), expected, rtol=1e-6, atol=1e-6)
    plain = _job(api, scene_id, camera)
    missing = api.client.get(f"/v1/jobs/{plain['job_id']}/result", params={"format": "normal"})
    assert missing.status_code == 409 and missing.json()["parameter"] == "format"
    bad = api.client.post("/v1/jobs", json={"scene_id": scene_id, "camera": camera,
                                            "passes": ["albedo"]})
    assert bad.status_code == 422 and "passes" in bad.json()["parameter"]
