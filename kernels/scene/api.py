"""numpy in, numpy out: `build_scene` and `trace` of a two-level scene (contract in
docs/kernels-api.md)."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from ..bvh.api import METHODS, Bvh, build_over_boxes
from ..bvh.api import trace as trace_bvh
from ..bvh.binary_traversal import STACK_SIZE
from ..bvh.node import empty_root
from ..bvh.packet import PACKET
from ..core.claim import claimed_arg, launch_claimed
from ..core.hits import Hits
from ..core.launch import get_device, host_threads, load_modules, sync_ms
from ..core.validate import (
    as_rays_unread,
    as_shading,
    as_terminator_offsets,
    ray_range,
    refuse_flagged_rays,
)
from . import instances as inst
from .packet import WARP_MODULES as PACKET_MODULES
from .packet import instance_packets, scene_packet_kernel, scene_packets_apply, scratch_arrays
from .stats import SceneStats
from .top import (
    WARP_MODULES,
    InstanceRecord,
    MeshRecord,
    SceneArrays,
    SceneShading,
    scene_trace_kernel,
)

TOP_LEAF_SIZE = 1  # instances per top-level leaf: each is box-tested before its ray turns


@dataclass
class Scene:
    """Meshes' BVHs (object space) and instances of them, with the top level over the
    instances. `bounds` (2, 3) is the world box of every instance (culled ones too: see
    `build_scene`'s `visible`), the scene default AO distance's box. A mesh left unbuilt
    (None: no instance of it in view) is in `meshes` as None."""

    meshes: list[Bvh | None]
    mesh_ids: np.ndarray  # (I,) int32
    transforms: np.ndarray  # (I, 3, 4) float32 object-to-world
    device: wp.context.Device
    arrays: SceneArrays
    bounds: np.ndarray  # (2, 3) float32
    instance_boxes: np.ndarray  # (I, 2, 3) float32 world boxes, padded (instances.py)
    frames: dict  # instances.instance_frames: float64 M, A, T, C per instance
    stats: SceneStats | None = None  # build_scene's
    shading_cache: dict = field(default_factory=dict, repr=False)  # render.ao's, by inputs

    def shading(self, normals, terminator_offset) -> SceneShading:
        """The device form of per-mesh shading normals (`normals`: None, or one entry per
        mesh, each None or (T_k, 3, 3) as `render_ao`'s for one mesh, in object space) and
        per-instance terminator offsets (a number or (I,)): made for the first call with
        these objects and kept (arrays are taken as read-only)."""
        key = (id(normals), terminator_offset if np.isscalar(terminator_offset)
               else id(terminator_offset))
        if key in self.shading_cache:
            return self.shading_cache[key][1]
        per_mesh = [None] * len(self.meshes) if normals is None else list(normals)
        if len(per_mesh) != len(self.meshes):
            raise ValueError(f"normals must be None or hold one entry per mesh "
                             f"({len(self.meshes)}), got {len(per_mesh)}")
        offsets = as_terminator_offsets(terminator_offset, len(self.mesh_ids), "instance")
        corners, base, start = [], np.full(len(self.meshes), -1, np.int32), 0
        for k, (n, bvh) in enumerate(zip(per_mesh, self.meshes, strict=True)):
            if bvh is None:  # no instance of it in the top level: never shaded
                continue
            checked = as_shading(n, 0.0, len(bvh.indices))
            if checked is not None:
                base[k] = start
                corners.append(checked[0].reshape(-1, 3))
                start += len(corners[-1])
        out = SceneShading()
        out.smooth = int(bool(corners))
        out.normals = wp.array(np.concatenate(corners) if corners else np.zeros((1, 3),
                               np.float32), dtype=wp.vec3, device=self.device)
        out.base = wp.array(base, dtype=int, device=self.device)
        out.offsets = wp.array(offsets if len(offsets) else np.zeros(1, np.float32),
                               dtype=float, device=self.device)
        self.shading_cache.clear()  # one set kept, as DeviceMesh keeps one
        self.shading_cache[key] = ((normals, terminator_offset), out)
        return out

    @property
    def nbytes(self) -> int:
        """Device bytes of the scene: each mesh's BVH and mesh arrays once (however many
        instances use it), the instances and the top level."""
        own = [self.arrays.top, self.arrays.top_ids, self.arrays.instances, self.arrays.meshes]
        return sum(a.capacity for a in own) + sum(bvh_nbytes(b) for b in self.meshes
                                                  if b is not None)


@dataclass
class Placement:
    """Instances placed in the world, before any BVH: the meshes' object boxes (K, 2, 3),
    validated mesh ids and transforms, their float64 frames (`instances.instance_frames`),
    the padded world boxes (I, 3) lo and hi the top level is built over, which instances
    have triangles (`valid`), and `bounds` (2, 3): the unpadded world box of the valid ones
    (the scene's `bounds`)."""

    mesh_bounds: np.ndarray
    mesh_ids: np.ndarray
    transforms: np.ndarray
    frames: dict
    lo: np.ndarray
    hi: np.ndarray
    valid: np.ndarray
    bounds: np.ndarray


def place_instances(mesh_bounds: np.ndarray, mesh_ids, transforms) -> Placement:
    """The instances of meshes with object boxes `mesh_bounds` (K, 2, 3) float32 (a Bvh's
    `bounds`, or `cull.mesh_box` of its mesh data: the same box) placed in the world."""
    mesh_bounds = np.asarray(mesh_bounds, np.float32).reshape(-1, 2, 3)
    ids, transforms = inst.as_instances(mesh_ids, transforms, len(mesh_bounds))
    frames = inst.instance_frames(transforms)
    lo, hi, unpadded, valid = inst.world_boxes(frames, ids, mesh_bounds)
    if valid.any():
        bounds = np.stack([unpadded[valid, 0].min(0), unpadded[valid, 1].max(0)])
    else:
        bounds = np.full((2, 3), np.inf, np.float32)
    return Placement(mesh_bounds=mesh_bounds, mesh_ids=ids, transforms=transforms,
                     frames=frames, lo=lo, hi=hi, valid=valid, bounds=bounds.astype(np.float32))


def bvh_nbytes(bvh: Bvh) -> int:
    """Device bytes of one BVH: its arrays and its mesh's."""
    a = bvh.arrays
    arrays = (a.nodes, a.tri_verts, a.tri_ids, a.wide, a.blocks)
    return sum(x.capacity for x in arrays) + (bvh.mesh.nbytes if bvh.mesh is not None else 0)


def mesh_records(meshes: Sequence[Bvh | None]) -> np.ndarray:
    """The meshes' MeshRecords (addresses of their arrays: the Bvhs must outlive the scene;
    zeros for a mesh left unbuilt, which no instance in the top level refers to)."""
    recs = np.zeros(len(meshes), dtype=MeshRecord.numpy_dtype())
    for k, bvh in enumerate(meshes):
        if bvh is None:
            continue
        if bvh.mesh is None:
            raise ValueError(f"meshes[{k}] has no device mesh (bvh.mesh): build it with "
                             "build_bvh")
        recs[k] = mesh_record(bvh, recs[k:k + 1])
    return recs


def mesh_record(bvh: Bvh, rec: np.ndarray) -> np.ndarray:
    """`rec` (one MeshRecord row) filled from a Bvh."""
    a = bvh.arrays
    for name, arr in (("nodes", a.nodes), ("tri_verts", a.tri_verts), ("tri_ids", a.tri_ids),
                      ("wide", a.wide), ("blocks", a.blocks), ("vertices", bvh.mesh.v),
                      ("indices", bvh.mesh.f)):
        rec[name] = arr.ptr
    rec["node_count"] = a.nodes.shape[0]
    rec["tri_verts_count"] = a.tri_verts.shape[0]
    rec["tri_count"] = a.tri_ids.shape[0]
    rec["wide_count"] = a.wide.shape[0]
    rec["blocks_count"] = a.blocks.shape[0]
    rec["vertex_count"] = bvh.mesh.v.shape[0]
    rec["index_count"] = bvh.mesh.f.shape[0]
    rec["width"] = a.width
    return rec


def build_scene(meshes: Sequence[Bvh | None], mesh_ids, transforms, *,
                visible: np.ndarray | None = None, placed: Placement | None = None,
                device=None, method: str = "sah", workers: int | None = None) -> Scene:
    """A two-level scene: instance i is `meshes[mesh_ids[i]]` (a Bvh from `build_bvh`, in
    object space) under the 3x4 object-to-world `transforms[i]` (float32 rows [M | T];
    mirrored and non-uniform scales allowed, singular ones rejected). The meshes' arrays are
    shared, not copied: N instances of a mesh hold its data once; keep the Bvh objects
    alive and unchanged but for `refit_bvh` (which updates them in place; rebuild the scene
    afterwards, for the new boxes). The top level is built on the task pool over the
    instances' padded world boxes. `visible` (I,) bool, e.g. from `cull.visible_instances`:
    instances left out of the top level (their indices stay those of the full list).
    `placed`: these instances' `place_instances` (what `visible` was decided on), used
    instead of placing them again where its boxes are the built meshes'. A mesh with no
    visible instance may be None (left unbuilt), its box then `placed`'s, which the scene's
    `bounds` count; `device` says where the scene lives when every mesh is None."""
    if not meshes:
        raise ValueError("meshes must hold at least one Bvh (build_bvh of each mesh)")
    if method not in METHODS:
        raise ValueError(f"method must be one of {sorted(METHODS)}, got {method!r}")
    built = [b for b in meshes if b is not None]
    device = built[0].device if built else get_device(device)
    if any(b.device != device for b in built):
        raise ValueError("every mesh's Bvh must be on the same device")
    compile_ms = load_modules(device, *WARP_MODULES)
    t_total = time.perf_counter()
    phase_ms: dict[str, float] = {}
    unbuilt = np.array([b is None for b in meshes])
    if placed is not None and (placed.mesh_bounds.shape != (len(meshes), 2, 3)
                               or not np.array_equal(placed.mesh_ids, mesh_ids)
                               or not np.array_equal(placed.transforms, transforms)):
        raise ValueError("placed must be place_instances of these meshes' boxes, mesh_ids "
                         "and transforms")
    if unbuilt.any() and placed is None:
        raise ValueError("a mesh is None (unbuilt): pass placed (place_instances of the "
                         "meshes' boxes, cull.mesh_box) for its box")
    boxes = np.stack([placed.mesh_bounds[k] if b is None else np.asarray(b.bounds, np.float32)
                      for k, b in enumerate(meshes)])
    if placed is None or not np.array_equal(boxes, placed.mesh_bounds):
        placed = place_instances(boxes, mesh_ids, transforms)
    ids, n = placed.mesh_ids, len(placed.mesh_ids)
    if visible is not None:
        visible = np.asarray(visible)
        if visible.shape != (n,) or visible.dtype != bool:
            raise ValueError(f"visible must be a ({n},) bool array (one per instance), got "
                             f"shape {visible.shape} dtype {visible.dtype}")
    needed = unbuilt[ids] if visible is None else unbuilt[ids] & visible
    if needed.any():
        i = int(np.flatnonzero(needed)[0])
        raise ValueError(f"instance {i} is visible but its mesh {ids[i]} is None: build it, "
                         "or leave the instance out (visible)")
    frames, lo, hi, valid = placed.frames, placed.lo, placed.hi, placed.valid
    keep = valid if visible is None else valid & visible
    records = np.zeros(n, dtype=InstanceRecord.numpy_dtype())
    records["lin"] = frames["lin"]
    records["inv"] = frames["inv"]
    records["normal"] = np.transpose(frames["inv"], (0, 2, 1))
    records["trans"] = frames["trans"]
    records["mesh"] = ids
    gram = np.einsum("nji,njk->nik", frames["lin"], frames["lin"])
    records["rescale"] = ~np.all(gram == np.eye(3), axis=(1, 2))
    phase_ms["instances"] = (time.perf_counter() - t_total) * 1e3

    t0 = time.perf_counter()
    mid = 0.5 * (lo.astype(np.float64) + hi)
    inf = np.float32(np.inf)
    if keep.any():
        box = np.array([lo[keep].min(0), hi[keep].max(0), mid[keep].min(0), mid[keep].max(0)],
                       np.float32)
    else:
        box = np.array([[inf] * 3, [-inf] * 3, [inf] * 3, [-inf] * 3], np.float32)
    tree = build_over_boxes(lo, hi, keep, box, method, TOP_LEAF_SIZE, STACK_SIZE, device,
                            workers=workers, phase_ms=phase_ms, start=t0)
    arrays = SceneArrays()
    if tree.count:
        arrays.top = tree.data.nodes[: tree.node_count]
        top_ids = np.ascontiguousarray(tree.data.items.numpy()["tri"][: tree.count], np.int32)
    else:
        arrays.top = empty_root(device)
        top_ids = np.zeros(1, np.int32)
    arrays.top_ids = wp.array(top_ids, dtype=int, device=device)
    arrays.instances = wp.array(records, dtype=InstanceRecord, device=device)
    arrays.meshes = wp.array(mesh_records(meshes), dtype=MeshRecord, device=device)
    arrays.slope = inst.slope(frames)
    phase_ms["top"] = sync_ms(device, t0)
    scene = Scene(meshes=list(meshes), mesh_ids=ids, transforms=placed.transforms,
                  device=device, arrays=arrays, bounds=placed.bounds,
                  instance_boxes=np.stack([lo, hi], axis=1), frames=frames)
    scene.stats = SceneStats(
        build_ms=(time.perf_counter() - t_total) * 1e3, compile_ms=compile_ms,
        phase_ms=phase_ms, instances=n, instances_built=int(keep.sum()), meshes=len(meshes),
        meshes_built=len(built), top_nodes=tree.node_count if tree.count else 1,
        top_depth=tree.depth, nbytes=scene.nbytes, device=str(device))
    return scene


def trace(
    scene: Bvh | Scene,
    origins: np.ndarray,
    directions: np.ndarray,
    tmin: float | np.ndarray = 0.0,
    tmax: float | np.ndarray = np.inf,
    any_hit: bool = False,
    *,
    threads: int | None = None,
    packets: bool = True,
) -> Hits:
    """Closest hit (or, with any_hit, some hit) per ray in [tmin, tmax] through a `Bvh`
    (kernels.bvh.trace) or a two-level `Scene`; `packets` says whether coherent runs of 64
    closest-hit rays may go as packets (the same hits; False: ray by ray). Through a
    scene, `triangle` is the index in the hit instance's mesh, `instance` the instance (-1
    on a miss; at equal t the lowest), t the world ray's parameter and (u, v) the
    barycentrics (the same in object and world space)."""
    if isinstance(scene, Bvh):
        return trace_bvh(scene, origins, directions, tmin, tmax, any_hit, threads=threads,
                         packets=packets)
    if not isinstance(scene, Scene):
        raise ValueError(f"trace takes a Bvh (build_bvh) or a Scene (build_scene), got "
                         f"{type(scene).__name__}")
    origins, directions = as_rays_unread(origins, directions)  # the kernel checks them
    r = len(origins)
    tmin_a, tmax_a = ray_range(tmin, tmax, r, keep_scalar=True)
    device = scene.device
    load_modules(device, *WARP_MODULES)
    out = [np.empty(r, dt) for dt in (np.float32, np.int32, np.float32, np.float32, np.int32)]
    outputs = [claimed_arg(x, dt, device) for x, dt in zip(out, (float, int, float, float, int),
                                                              strict=True)]
    inputs = [claimed_arg(origins, wp.vec3, device), claimed_arg(directions, wp.vec3, device),
              claimed_arg(tmin_a, float, device), claimed_arg(tmax_a, float, device)]
    invalid = claimed_arg(np.zeros(1, np.int32), int, device)
    nthreads = host_threads(device, threads)
    if any_hit or not (packets and scene_packets_apply(device)):
        launch_claimed(scene_trace_kernel, r, [scene.arrays, *inputs, int(any_hit), *outputs,
                                               invalid], device, nthreads)
    else:
        load_modules(device, *PACKET_MODULES)
        scratch = scratch_arrays(instance_packets(r, device))
        launch_claimed(scene_packet_kernel, r, [scene.arrays, *inputs, *scratch, *outputs,
                                                invalid], device, nthreads, align=PACKET)
    refuse_flagged_rays(invalid, origins, directions)
    if not device.is_cpu:
        out = [a.numpy() for a in outputs]
    return Hits(t=out[0], triangle=out[1], u=out[2], v=out[3], instance=out[4])
