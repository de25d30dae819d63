"""Binary wire format of the service: decode, validate and encode little-endian arrays.

Everything here is plain numpy and raises `ApiError` (wire/problems.py: a 4xx naming
the parameter and the fix) for client mistakes, so the routes stay thin and the rules are
testable without a server. Layouts (also in docs/api.md):

- scene body: V*3 float32 positions, then T*3 int32 indices, then (with `normals`) T*9
  float32 shading normals, corner by corner, then (with `terminator_offsets`, only with
  normals) T float32 shadow terminator offsets; little-endian, no padding.
- mesh body (`PUT /v1/meshes/{id}`): the scene body's layout, in the mesh's own space.
- instance list: K*32 ASCII hex mesh ids, then N int32 mesh indices (into those ids), then
  N*12 float32 object-to-world transforms (3x4, row-major), then (with `visibility`) N
  uint8 ray visibility masks (VISIBILITY_BITS), little-endian, no padding.
- ray body: R*6 float32 (origin xyz, direction xyz per ray), little-endian.
- AO result: R float32, little-endian.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scenesort.backend.wire.problems import ApiError

from scenesort.ao_options import AO_OPTIONS

F32 = np.dtype("<f4")
I32 = np.dtype("<i4")
SCENE_HASH_CHARS = 32  # hex characters kept from the sha256 digest (128 bits)
MAX_INDEXABLE_VERTICES = 2**31 - 1  # indices are int32


@dataclass(frozen=True)
class SceneArrays:
    """A decoded, validated scene: vertices (N,3) float32, indices (M,3) int32, and
    optionally shading normals (M,3,3) float32 and terminator offsets (M,) float32."""

    vertices: np.ndarray
    indices: np.ndarray
    scene_id: str
    degenerate: int
    normals: np.ndarray | None = None
    terminator_offsets: np.ndarray | None = None

    @property
    def nbytes(self) -> int:
        extra = (self.normals, self.terminator_offsets)
        return int(self.vertices.nbytes + self.indices.nbytes
                   + sum(a.nbytes for a in extra if a is not None))

    @cached_property
    def bounds(self) -> list[list[float]]:
        """[[xmin, ymin, zmin], [xmax, ymax, zmax]] (per column: 15x faster than axis=0)."""
        columns = self.vertices.T
        return [[float(c.min()) for c in columns], [float(c.max()) for c in columns]]

    @cached_property
    def topology(self) -> str:
        """Id of the mesh's connectivity (vertex count and indices): meshes that share it
        differ only in positions (and normals), so one's BVH refits into the other's."""
        digest = hashlib.sha256(b"scenesort-topology-v1 %d %d\n"
                                % (len(self.vertices), len(self.indices)))
        digest.update(self.indices.astype(I32).tobytes())
        return digest.hexdigest()[:SCENE_HASH_CHARS]


@dataclass(frozen=True, eq=False)  # by identity: render/ao.py keeps per list what it made
class InstanceScene:
    """A decoded instance list with its meshes resolved: instance i is `meshes[mesh_index[i]]`
    under the 3x4 object-to-world `transforms[i]` (float32, row-major)."""

    scene_id: str
    meshes: tuple[SceneArrays, ...]
    mesh_index: np.ndarray  # (N,) int32
    transforms: np.ndarray  # (N, 3, 4) float32
    visibility: np.ndarray | None = None  # (N,) uint8 masks; None: all DEFAULT_VISIBILITY

    @property
    def nbytes(self) -> int:
        """Bytes of the instance list itself; the meshes are store entries of their own."""
        masks = 0 if self.visibility is None else self.visibility.nbytes
        return int(self.mesh_index.nbytes + self.transforms.nbytes + masks)

    @property
    def instances(self) -> int:
        return len(self.mesh_index)

    @property
    def triangles(self) -> int:
        """Triangles the instances stand for (each instance counts its mesh once)."""
        counts = np.array([len(m.indices) for m in self.meshes], np.int64)
        return int(counts[self.mesh_index].sum())

    @property
    def vertices(self) -> int:
        counts = np.array([len(m.vertices) for m in self.meshes], np.int64)
        return int(counts[self.mesh_index].sum())

    @property
    def degenerate(self) -> int:
        counts = np.array([m.degenerate for m in self.meshes], np.int64)
        return int(counts[self.mesh_index].sum())

    @cached_property
    def bounds(self) -> list[list[float]]:
        """The world box of every instance's transformed mesh box (its 8 corners)."""
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for k, mesh in enumerate(self.meshes):
            chosen = self.transforms[self.mesh_index == k].astype(np.float64)
            if not len(chosen):
                continue
            box = np.array(mesh.bounds, np.float64)
            corners = np.array([[box[i, 0], box[j, 1], box[m, 2]]
                                for i in (0, 1) for j in (0, 1) for m in (0, 1)])
            world = corners @ chosen[:, :, :3].transpose(0, 2, 1) + chosen[:, None, :, 3]
            lo = np.minimum(lo, world.reshape(-1, 3).min(axis=0))
            hi = np.maximum(hi, world.reshape(-1, 3).max(axis=0))
        return [lo.tolist(), hi.tolist()]


def scene_hash(vertex_count: int, triangle_count: int, body: bytes | memoryview) -> str:
    """Content id of a scene: sha256 of b"scenesort-scene-v1 V T\\n" + body, first 32 hex.

    The counts are hashed because the same bytes split differently are a different
    scene; the body's length then says which optional blocks it holds (normals: 36*T
    bytes, terminator offsets: 4*T), so they are covered too. The add-on computes the same
    value to skip uploading an unchanged scene.
    """
    digest = hashlib.sha256(b"scenesort-scene-v1 %d %d\n" % (vertex_count, triangle_count))
    digest.update(body)
    return digest.hexdigest()[:SCENE_HASH_CHARS]


def instances_hash(mesh_count: int, instance_count: int, body: bytes | memoryview) -> str:
    """Content id of an instance list: sha256 of b"scenesort-instances-v1 K N\\n" + body,
    first 32 hex. It names the meshes by their ids, so a changed mesh is a new list."""
    digest = hashlib.sha256(b"scenesort-instances-v1 %d %d\n" % (mesh_count, instance_count))
    digest.update(body)
    return digest.hexdigest()[:SCENE_HASH_CHARS]


def expect_body_length(parameter: str, body_len: int, expected: int, layout: str) -> None:
    """Reject a body whose length does not match what the counts promise."""
    if body_len != expected:
        raise ApiError(
            400,
            "body",
            f"body is {body_len} bytes but {parameter} promise {expected} bytes ({layout})",
            f"send exactly {expected} bytes, or correct {parameter} to match the body",
            "bad_body_length",
        )


def _check_finite(parameter: str, values: np.ndarray, what: str) -> None:
    bad = ~np.isfinite(values)
    if bad.any():
        row = int(np.argmax(bad.reshape(len(values), -1).any(axis=1)))
        raise ApiError(
            400,
            parameter,
            f"{what} {row} is not finite ({values[row].tolist()}): NaN and Inf are not allowed",
            f"replace NaN/Inf values in {what} {row} (and any others) with finite numbers",
            "not_finite",
        )


def scene_body_length(vertex_count: int, triangle_count: int, normals: bool = False,
                      terminator_offsets: bool = False) -> int:
    """Bytes of a scene upload with these counts and optional blocks."""
    return 12 * vertex_count + (12 + 36 * normals + 4 * terminator_offsets) * triangle_count


def check_blocks(normals: bool, terminator_offsets: bool) -> None:
    """Terminator offsets shape the normals' smooth surface: refuse them alone."""
    if terminator_offsets and not normals:
        raise ApiError(
            422, "terminator_offsets",
            "terminator offsets apply to smooth-shaded triangles, but the upload has no normals",
            "send normals=true with the normal block, or drop terminator_offsets",
            "invalid_parameter",
        )


def decode_scene(
    body: bytes, vertex_count: int, triangle_count: int, scene_id: str | None = None, *,
    normals: bool = False, terminator_offsets: bool = False,
    count_degenerate: Callable[[np.ndarray, np.ndarray], int],
) -> SceneArrays:
    """Decode and validate a scene upload; raise `ApiError` naming the bad part.

    `scene_id` is `scene_hash(...)` of the same body when the caller has it already;
    `normals`, `terminator_offsets`: whether the body holds those blocks. Zero-area
    triangles are the engine's to count (render.engine.count_degenerate): this module
    imports no engine."""
    check_blocks(normals, terminator_offsets)
    layout = f"{vertex_count}*3 float32 + {triangle_count}*3 int32"
    layout += f" + {triangle_count}*9 float32 normals" if normals else ""
    layout += f" + {triangle_count} float32 terminator offsets" if terminator_offsets else ""
    expected = scene_body_length(vertex_count, triangle_count, normals, terminator_offsets)
    expect_body_length("vertices and triangles", len(body), expected, layout)
    split = 12 * vertex_count
    vertices = np.frombuffer(body, F32, count=3 * vertex_count).reshape(-1, 3)
    indices = np.frombuffer(body, I32, count=3 * triangle_count, offset=split).reshape(-1, 3)
    _check_finite("body (vertices)", vertices, "vertex")
    lo, hi = int(indices.min()), int(indices.max())
    if lo < 0 or hi >= vertex_count:
        bad = lo if lo < 0 else hi
        row = int(np.argmax((indices == bad).any(axis=1)))
        raise ApiError(
            400,
            "body (indices)",
            f"triangle {row} has index {bad}, outside 0..{vertex_count - 1}"
            f" (vertices={vertex_count})",
            "indices must be 0-based int32 into the vertex array; fix the triangle or raise"
            " vertices",
            "index_out_of_range",
        )
    # Native-order copies: the engine wants plain float32/int32 and owns its arrays.
    vertices = vertices.astype(np.float32)
    indices = indices.astype(np.int32)
    at = 12 * (vertex_count + triangle_count)
    corner_normals = offsets = None
    if normals:
        corner_normals = np.frombuffer(body, F32, count=9 * triangle_count, offset=at)
        corner_normals = corner_normals.reshape(-1, 3, 3)
        _check_finite("body (normals)", corner_normals, "the normal block of triangle")
        corner_normals = corner_normals.astype(np.float32)
        at += 36 * triangle_count
    if terminator_offsets:
        offsets = np.frombuffer(body, F32, count=triangle_count, offset=at).astype(np.float32)
        spec = AO_OPTIONS["terminator_offset"]
        bad = ~spec.within(offsets)  # NaN fails too
        if bad.any():
            row = int(np.argmax(bad))
            raise ApiError(
                400, "body (terminator offsets)",
                f"triangle {row} has terminator offset {float(offsets[row])}, not "
                f"{spec.takes()}",
                f"send Blender's Shadow Terminator Geometry Offset ({spec.takes()}) for every "
                "triangle",
                "bad_terminator_offset",
            )
    return SceneArrays(
        vertices=vertices,
        indices=indices,
        scene_id=scene_id or scene_hash(vertex_count, triangle_count, body),
        degenerate=count_degenerate(vertices, indices),
        normals=corner_normals,
        terminator_offsets=offsets,
    )


MESH_ID_BYTES = SCENE_HASH_CHARS  # a mesh id travels as its 32 ASCII hex characters
_HEX = frozenset(b"0123456789abcdef")


# An instance's ray visibility mask, as Cycles' AO pass reads an object's: seen by camera
# rays, met by occlusion (shadow) rays, and held out where the camera sees it.
CAMERA, SHADOW, HOLDOUT = 1, 2, 4
VISIBILITY_BITS = CAMERA | SHADOW | HOLDOUT
DEFAULT_VISIBILITY = CAMERA | SHADOW  # an instance list sent without masks


def instance_body_length(mesh_count: int, instance_count: int,
                         visibility: bool = False) -> int:
    """Bytes of an instance list with K mesh ids and N instances (and their masks)."""
    return MESH_ID_BYTES * mesh_count + (53 if visibility else 52) * instance_count


@dataclass(frozen=True)
class InstanceList:
    """A decoded, validated instance list whose meshes are still ids."""

    scene_id: str
    mesh_ids: tuple[str, ...]
    mesh_index: np.ndarray  # (N,) int32 into mesh_ids
    transforms: np.ndarray  # (N, 3, 4) float32
    visibility: np.ndarray | None = None  # (N,) uint8 masks; None: all DEFAULT_VISIBILITY


def decode_instances(body: bytes, mesh_count: int, instance_count: int,
                     visibility: bool = False) -> InstanceList:
    """Decode and validate an instance list (layout in the module docstring); raise
    `ApiError` naming the bad part. Its id is `instances_hash` of the body."""
    layout = (f"{mesh_count}*32 hex mesh ids + {instance_count} int32 mesh indices"
              f" + {instance_count}*12 float32 transforms"
              + (f" + {instance_count} uint8 visibility masks" if visibility else ""))
    expected = instance_body_length(mesh_count, instance_count, visibility)
    expect_body_length("meshes and instances", len(body), expected, layout)
    ids = []
    for k in range(mesh_count):
        raw = body[MESH_ID_BYTES * k:MESH_ID_BYTES * (k + 1)]
        if not _HEX.issuperset(raw):
            raise ApiError(
                400, "body (mesh ids)",
                f"mesh id {k} ({bytes(raw)[:32]!r}) is not 32 lowercase hex characters",
                "send each mesh's id as PUT /v1/meshes/{mesh_id} names it (docs/api.md)",
                "bad_mesh_id",
            )
        ids.append(bytes(raw).decode("ascii"))
    at = MESH_ID_BYTES * mesh_count
    mesh_index = np.frombuffer(body, I32, count=instance_count, offset=at).astype(np.int32)
    bad = (mesh_index < 0) | (mesh_index >= mesh_count)
    if bad.any():
        row = int(np.argmax(bad))
        raise ApiError(
            400, "body (mesh indices)",
            f"instance {row} refers to mesh {int(mesh_index[row])}, outside 0..{mesh_count - 1}"
            f" (meshes={mesh_count})",
            "mesh indices are 0-based into the body's mesh ids; fix the instance or raise meshes",
            "index_out_of_range",
        )
    at += 4 * instance_count
    transforms = np.frombuffer(body, F32, count=12 * instance_count, offset=at)
    transforms = transforms.reshape(-1, 3, 4)
    _check_finite("body (transforms)", transforms, "the transform of instance")
    transforms = transforms.astype(np.float32)
    singular = np.linalg.det(transforms[:, :, :3].astype(np.float64)) == 0.0
    if singular.any():
        row = int(np.argmax(singular))
        raise ApiError(
            400, "body (transforms)",
            f"the transform of instance {row} is singular (its 3x3 part has determinant 0): "
            "rays cannot be taken into its space",
            "leave out instances scaled to nothing (their triangles have no area)",
            "singular_transform",
        )
    masks = None
    if visibility:
        at += 48 * instance_count
        masks = np.frombuffer(body, np.uint8, count=instance_count, offset=at).copy()
        unknown = (masks & ~VISIBILITY_BITS) != 0
        if unknown.any():
            row = int(np.argmax(unknown))
            raise ApiError(
                400, "body (visibility masks)",
                f"instance {row} has visibility mask {int(masks[row])}, with bits outside "
                f"{VISIBILITY_BITS} (1 camera, 2 shadow, 4 holdout)",
                "send each mask as the sum of the bits that apply (docs/api.md)",
                "invalid_parameter",
            )
        if (masks == DEFAULT_VISIBILITY).all():
            masks = None  # the same render as without masks (the id still differs)
    return InstanceList(instances_hash(mesh_count, instance_count, body), tuple(ids),
                        mesh_index, transforms, masks)


def resolve(listing: InstanceList,
            mesh: Callable[[str], SceneArrays | None]) -> InstanceScene:
    """The instance list with its meshes looked up by id (`mesh` returns None for one it
    lacks: KeyError naming the first such id). ValueError for a mesh whose terminator
    offsets vary over its triangles: an instance has one (Blender's is per object)."""
    meshes = []
    for k, mesh_id in enumerate(listing.mesh_ids):
        found = mesh(mesh_id)
        if found is None:
            raise KeyError(mesh_id)
        offsets = found.terminator_offsets
        if offsets is not None and np.any(offsets != offsets[0]):
            raise ValueError(f"mesh {k} ({mesh_id}) has terminator offsets that vary over "
                             "its triangles; in an instance list each mesh has one (send it "
                             "repeated, as the object's value)")
        meshes.append(found)
    return InstanceScene(listing.scene_id, tuple(meshes), listing.mesh_index,
                         listing.transforms, listing.visibility)


def decode_rays(body: bytes, ray_count: int) -> tuple[np.ndarray, np.ndarray]:
    """Decode R*6 float32 rays into (origins, directions), each (R,3) float32."""
    expect_body_length("rays", len(body), 24 * ray_count, f"{ray_count}*6 float32")
    rays = np.frombuffer(body, F32).reshape(-1, 6)  # a read-only view of the body
    _check_finite("body (rays)", rays, "ray")
    # One native-order copy per half: what the engine takes (and may write to).
    origins = rays[:, :3].astype(np.float32, order="C")
    directions = rays[:, 3:].astype(np.float32, order="C")
    zero = (directions[:, 0] == 0) & (directions[:, 1] == 0) & (directions[:, 2] == 0)
    if zero.any():
        row = int(np.argmax(zero))
        raise ApiError(
            400,
            "body (rays)",
            f"ray {row} has a zero-length direction {directions[row].tolist()}",
            "give every ray a nonzero direction (it need not be unit length)",
            "zero_direction",
        )
    return origins, directions


SURFACE_POINTS_LAYOUT = ("P little-endian int32 triangle indices (the scene's triangles in "
                         "upload order), then P float32 u, then P float32 v: the barycentric "
                         "weights of each triangle's second and third corner")


def decode_surface_points(body: bytes, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Decode P surface points (`SURFACE_POINTS_LAYOUT`) into (triangles, u, v); whether
    they lie on the scene's triangles the engine checks."""
    expect_body_length("points", len(body), 12 * count, f"{count}*(int32 + 2 float32)")
    triangles = np.frombuffer(body, I32, count).astype(np.int32)
    uv = np.frombuffer(body, F32, 2 * count, offset=4 * count).reshape(2, count)
    _check_finite("body (points)", uv.T, "point")
    return triangles, uv[0].astype(np.float32), uv[1].astype(np.float32)


def encode_f32(values: np.ndarray) -> bytes:
    """Little-endian float32 bytes of `values` (flattened, C order)."""
    return np.ascontiguousarray(values, dtype=F32).tobytes()


def encode_png(ao: np.ndarray) -> bytes:
    """An 8-bit grayscale PNG of a (height, width) AO image; values clipped to [0, 1].

    Row 0 is the top of the image (the camera model's order), as PNG stores it.
    """
    import io

    from PIL import Image

    pixels = np.round(np.clip(np.nan_to_num(ao, nan=0.0), 0.0, 1.0) * 255.0).astype(np.uint8)
    buffer = io.BytesIO()
    Image.fromarray(pixels, mode="L").save(buffer, format="PNG")
    return buffer.getvalue()
