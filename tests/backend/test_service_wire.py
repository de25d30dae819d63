"""The wire format's decoding and validation rules (backend/wire/binary.py), without a
server."""

from __future__ import annotations

import hashlib
from functools import partial

import numpy as np
import pytest
from scenesort.backend.render.ao import shading
from scenesort.backend.render.engine import count_degenerate
from scenesort.backend.wire import binary as wire
from scenesort.backend.wire.problems import ApiError

decode = partial(wire.decode_scene, count_degenerate=count_degenerate)  # as the service does

V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0]], np.float32)
IDX = np.array([[0, 1, 2], [0, 1, 3]], np.int32)  # the second is collinear: zero area


def body(v: np.ndarray = V, i: np.ndarray = IDX) -> bytes:
    return v.astype("<f4").tobytes() + i.astype("<i4").tobytes()


def test_scene_round_trips_and_counts_degenerate_triangles() -> None:
    scene = decode(body(), 4, 2)
    np.testing.assert_array_equal(scene.vertices, V)
    np.testing.assert_array_equal(scene.indices, IDX)
    assert scene.vertices.dtype == np.float32 and scene.indices.dtype == np.int32
    assert scene.degenerate == 1
    assert scene.bounds == [[0.0, 0.0, 0.0], [2.0, 1.0, 0.0]]


def test_scene_hash_is_the_documented_formula() -> None:
    """docs/api.md: sha256(b"scenesort-scene-v1 V T\\n" + body), first 32 hex characters."""
    expected = hashlib.sha256(b"scenesort-scene-v1 4 2\n" + body()).hexdigest()[:32]
    assert decode(body(), 4, 2).scene_id == expected


def test_same_bytes_with_other_counts_are_another_scene() -> None:
    data = np.zeros(6, "<f4").tobytes()  # 24 bytes: (V=1,T=1) or (V=2,T=0)
    assert wire.scene_hash(1, 1, data) != wire.scene_hash(2, 0, data)


@pytest.mark.parametrize(
    ("data", "vertices", "triangles", "parameter", "code"),
    [
        (body()[:-1], 4, 2, "body", "bad_body_length"),
        (body() + b"\0" * 12, 4, 2, "body", "bad_body_length"),
        (body(V * np.float32(np.nan)), 4, 2, "body (vertices)", "not_finite"),
        (body(V, IDX - 1), 4, 2, "body (indices)", "index_out_of_range"),
        (body(V, IDX + 2), 4, 2, "body (indices)", "index_out_of_range"),
    ],
    ids=["short", "long", "nan", "negative-index", "index-past-end"],
)
def test_bad_scenes_name_the_part(data, vertices, triangles, parameter, code) -> None:
    with pytest.raises(ApiError) as info:
        decode(data, vertices, triangles)
    assert (info.value.parameter, info.value.code) == (parameter, code)
    assert 400 <= info.value.status < 500 and info.value.fix


def test_index_error_names_the_triangle() -> None:
    with pytest.raises(ApiError, match="triangle 1 has index 7"):
        decode(body(V, np.array([[0, 1, 2], [0, 7, 3]], np.int32)), 4, 2)


NORMALS = np.arange(18, dtype=np.float32).reshape(2, 3, 3) / 17  # any finite numbers
OFFSETS = np.array([0.1, 0.5], np.float32)


def test_normal_and_terminator_blocks_follow_the_indices() -> None:
    """docs/api.md: T*9 float32 normals, then T float32 offsets; the id covers them."""
    data = body() + NORMALS.astype("<f4").tobytes() + OFFSETS.astype("<f4").tobytes()
    scene = decode(data, 4, 2, normals=True, terminator_offsets=True)
    np.testing.assert_array_equal(scene.normals, NORMALS)
    np.testing.assert_array_equal(scene.terminator_offsets, OFFSETS)
    assert scene.nbytes == len(data)
    assert shading(scene).keys() == {"normals", "terminator_offset"}
    assert scene.scene_id == hashlib.sha256(b"scenesort-scene-v1 4 2\n" + data).hexdigest()[:32]
    other = NORMALS.copy()
    other[1, 2, 0] += 1e-3
    changed = body() + other.astype("<f4").tobytes() + OFFSETS.astype("<f4").tobytes()
    assert wire.scene_hash(4, 2, changed) != scene.scene_id
    plain = decode(body(), 4, 2)
    assert plain.normals is None and shading(plain) == {}
    assert plain.scene_id != wire.scene_hash(4, 2, body() + NORMALS.tobytes())


@pytest.mark.parametrize(
    ("blocks", "flags", "parameter", "code"),
    [
        (NORMALS.tobytes(), {}, "body", "bad_body_length"),
        (b"", {"normals": True}, "body", "bad_body_length"),
        (np.full((2, 3, 3), np.inf, np.float32).tobytes(), {"normals": True}, "body (normals)",
         "not_finite"),
        (NORMALS.tobytes() + np.float32([0.1, 1.5]).tobytes(),
         {"normals": True, "terminator_offsets": True}, "body (terminator offsets)",
         "bad_terminator_offset"),
        (np.float32([0.1, 0.1]).tobytes(), {"terminator_offsets": True},
         "terminator_offsets", "invalid_parameter"),
    ],
    ids=["normals-unannounced", "normals-missing", "normals-inf", "offset-over-1",
         "offsets-without-normals"],
)
def test_bad_shading_blocks_name_the_part(blocks, flags, parameter, code) -> None:
    with pytest.raises(ApiError) as info:
        decode(body() + blocks, 4, 2, **flags)
    assert (info.value.parameter, info.value.code) == (parameter, code)
    assert 400 <= info.value.status < 500 and info.value.fix


def test_rays_decode_in_order() -> None:
    rays = np.arange(12, dtype=np.float32).reshape(2, 6) + 1
    origins, directions = wire.decode_rays(rays.astype("<f4").tobytes(), 2)
    np.testing.assert_array_equal(origins, rays[:, :3])
    np.testing.assert_array_equal(directions, rays[:, 3:])


@pytest.mark.parametrize(
    ("row", "code"),
    [
        ([0, 0, 0, 0, 0, 0], "zero_direction"),
        ([0, 0, 0, -0.0, 0, -0.0], "zero_direction"),
        ([0, 0, np.inf, 0, 0, 1], "not_finite"),
        ([0, 0, 0, np.nan, 0, 1], "not_finite"),
    ],
)
def test_bad_rays_are_refused(row, code) -> None:
    rays = np.array([[0, 0, 0, 0, 0, 1], row], np.float32)
    with pytest.raises(ApiError) as info:
        wire.decode_rays(rays.astype("<f4").tobytes(), 2)
    assert info.value.code == code and "ray 1" in info.value.message


def test_tiny_directions_are_valid() -> None:
    """Directions need not be unit length; only an exactly zero vector is refused."""
    rays = np.array([[0, 0, 0, 0, 0, 1e-30]], np.float32)
    _, directions = wire.decode_rays(rays.tobytes(), 1)
    assert directions[0, 2] == np.float32(1e-30)


def test_encode_is_little_endian_float32() -> None:
    data = wire.encode_f32(np.array([1.0, 0.5], np.float64))
    assert data == np.array([1.0, 0.5], "<f4").tobytes()


def test_png_is_gray_rows_top_first() -> None:
    from io import BytesIO

    from PIL import Image

    ao = np.array([[0.0, 1.0], [0.5, 2.0]], np.float32)
    image = Image.open(BytesIO(wire.encode_png(ao)))
    assert image.mode == "L" and image.size == (2, 2)
    assert np.asarray(image).ravel().tolist() == [0, 255, 128, 255]


def test_degenerate_count_agrees_with_the_engine() -> None:
    """The upload's count must equal the BVH's `degenerate` statistic."""
    from tests.kernels.reference import degenerate_triangles

    rng = np.random.default_rng(0)
    vertices = rng.integers(-3, 3, (50, 3)).astype(np.float32)  # many collinear triples
    vertices[:5] *= np.float32(1e-20)  # tiny triangles whose float32 cross would underflow
    indices = rng.integers(0, 50, (20000, 3)).astype(np.int32)
    expected = int(np.count_nonzero(degenerate_triangles(vertices, indices)))
    assert 0 < count_degenerate(vertices, indices) == expected < len(indices)
