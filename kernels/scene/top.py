"""The two-level scene on the device: bottom-level BVHs by address, instances, and the
top-level traversal that carries each ray into the instances it may hit.

A mesh's BVH stays in its own arrays (`Bvh.arrays`); the scene holds one `MeshRecord` per
mesh with their addresses and sizes, and `mesh_view` turns a record back into the
`BvhArrays` that `bvh.traversal.traverse` reads (Warp structs cannot hold arrays of structs
with arrays, but a kernel can make an array from an address). So N instances of a mesh
share one copy of its data, and a refit (kernels.bvh.refit, in place) is seen by every
scene that holds the mesh.

Top level: a binary tree (`bvh.api.build_over_boxes`, the pool build over the instances'
padded world boxes) of one instance per leaf, traversed by the mesh BVH's own loop
(`bvh.binary_traversal`) with this level's box test and leaves. Its boxes are tested in
float64 with walls that move out with t (`enter_padded_box`, instances.py's bound); a
leaf's instance gets the ray in object space (`object_ray`) and the bottom-level traversal
of its mesh, with the closest hit so far as tmax, so t is the world ray's own parameter in
every instance.
"""

from __future__ import annotations

import warp as wp

from ..bvh.binary_traversal import BinaryTree, make_binary_traversal
from ..bvh.leaf import finish_traversal
from ..bvh.node import BvhArrays, BvhNode
from ..bvh.traversal import traverse_leaf_order
from ..core.box import INF
from ..core.claim import Claims, claimed_items
from ..core.compile_options import MODULE_OPTIONS
from ..core.ray import Hit, Ray, flag_invalid_rays, make_ray, per_ray

wp.set_module_options(MODULE_OPTIONS)

@wp.struct
class MeshRecord:
    """One bottom-level BVH by address: 112 bytes (seven 8-byte addresses, each followed by
    its int32 size padded to 8; `width` shares the last size's word pair). Sizes count
    elements of each array's own dtype."""

    nodes: wp.uint64  # BvhNode array
    node_count: int
    tri_verts: wp.uint64  # vec3, 3 per leaf position
    tri_verts_count: int
    tri_ids: wp.uint64  # int per leaf position: the mesh's triangle index
    tri_count: int
    wide: wp.uint64  # float words of the wide nodes (width > 2)
    wide_count: int
    blocks: wp.uint64  # float words of the leaf blocks
    blocks_count: int
    vertices: wp.uint64  # the mesh's vec3 vertices and vec3i triangles (surfaces)
    vertex_count: int
    indices: wp.uint64
    index_count: int
    width: int


@wp.struct
class InstanceRecord:
    """One instance: its mesh and transform, float64 (248 bytes: 3 mat33d, 1 vec3d, 2 int)."""

    lin: wp.mat33d  # M, object to world (the caller's float32 values)
    inv: wp.mat33d  # A = M^-1
    normal: wp.mat33d  # A^T: shading normals to world
    trans: wp.vec3d  # T
    mesh: int
    rescale: int  # 1 unless M is exactly orthogonal: world normals are then renormalised


@wp.struct
class SceneArrays:
    """What the scene's kernels read."""

    top: wp.array(dtype=BvhNode)  # the top level's nodes; a leaf holds one instance
    top_ids: wp.array(dtype=int)  # instance index per top-level leaf position
    instances: wp.array(dtype=InstanceRecord)
    meshes: wp.array(dtype=MeshRecord)
    slope: float  # instances.slope: the top level's walls per unit t per unit |d|


@wp.struct
class SceneShading:
    """Shading normals of a scene's meshes (object space) and its instances' terminator
    offsets; smooth 0 when no mesh has normals (the arrays then hold a dummy entry)."""

    normals: wp.array(dtype=wp.vec3)  # the meshes' corner normals one after the other
    base: wp.array(dtype=int)  # per mesh: its first entry in `normals`, -1 for none (flat)
    offsets: wp.array(dtype=float)  # per instance: Cycles' shadow terminator offset
    smooth: int


@wp.struct
class InstanceHit:
    hit: Hit  # t along the world ray; triangle: the instance's mesh's index
    instance: int  # -1 on a miss


@wp.func
def mesh_view(rec: MeshRecord) -> BvhArrays:
    """The BvhArrays of a mesh record: traverse reads them as it reads a single mesh's."""
    b = BvhArrays()
    b.nodes = wp.array(ptr=rec.nodes, shape=(rec.node_count,), dtype=BvhNode)
    b.tri_verts = wp.array(ptr=rec.tri_verts, shape=(rec.tri_verts_count,), dtype=wp.vec3)
    b.tri_ids = wp.array(ptr=rec.tri_ids, shape=(rec.tri_count,), dtype=int)
    b.wide = wp.array(ptr=rec.wide, shape=(rec.wide_count,), dtype=float)
    b.blocks = wp.array(ptr=rec.blocks, shape=(rec.blocks_count,), dtype=float)
    b.vertices = mesh_vertices(rec)
    b.indices = mesh_indices(rec)
    b.width = rec.width
    return b


@wp.func
def mesh_vertices(rec: MeshRecord) -> wp.array(dtype=wp.vec3):
    return wp.array(ptr=rec.vertices, shape=(rec.vertex_count,), dtype=wp.vec3)


@wp.func
def mesh_indices(rec: MeshRecord) -> wp.array(dtype=wp.vec3i):
    return wp.array(ptr=rec.indices, shape=(rec.index_count,), dtype=wp.vec3i)


@wp.func
def world_point(inst: InstanceRecord, p: wp.vec3) -> wp.vec3:
    """M p + T in float64, rounded once (the identity gives p back exactly)."""
    return wp.vec3(inst.lin * wp.vec3d(p) + inst.trans)


@wp.func
def world_normal(inst: InstanceRecord, n: wp.vec3) -> wp.vec3:
    """A unit shading normal to world space: by the inverse transpose, renormalised in
    float64 (as the mesh's own normals were) unless M keeps lengths exactly (then the
    normal comes back bit for bit under the identity, a mirror or an axis permutation)."""
    w = inst.normal * wp.vec3d(n)
    if inst.rescale != 0 and wp.length_sq(w) > wp.float64(0.0):
        w = wp.normalize(w)
    return wp.vec3(w)


@wp.func
def object_coords(inst: InstanceRecord, origin: wp.vec3, direction: wp.vec3):
    """The ray's origin and direction in the instance's object space, each coordinate
    computed in float64 and rounded once; the direction is not normalised, so t is the
    world ray's parameter."""
    o = inst.inv * (wp.vec3d(origin) - inst.trans)
    d = inst.inv * wp.vec3d(direction)
    return wp.vec3(o), wp.vec3(d)


@wp.func
def object_ray(inst: InstanceRecord, origin: wp.vec3, direction: wp.vec3) -> Ray:
    """The `Ray` of `object_coords`."""
    o, d = object_coords(inst, origin, direction)
    return make_ray(o, d)


@wp.struct
class TopRay:
    """A world ray as the top level takes it: float64 for the padded box test, float32 for
    the instances' object-space rays. The box test also takes a packet of rays as one
    (scene/packet.py): then the origins' bounds and the walls' rise and fall of the most
    extreme directions, a test that passes wherever one of the packet's rays passes."""

    origin: wp.vec3
    direction: wp.vec3
    o_low: wp.vec3d  # the origin (a packet's: the least coordinates)
    o_high: wp.vec3d  # the origin (a packet's: the greatest)
    rise: wp.vec3d  # d + s per axis, s the walls' speed: SceneArrays.slope times max |d|
    fall: wp.vec3d  # s - d
    inv_rise: wp.vec3d  # their reciprocals: a box test multiplies (no division)
    inv_fall: wp.vec3d


@wp.func
def clip_side(a: wp.float64, inv_a: wp.float64, b: wp.float64, t: wp.vec2d) -> wp.vec2d:
    """[t0, t1] intersected with {t : a t >= b} (empty: t0 > t1), inv_a = 1 / a: b inv_a is
    within 2 ulps (float64) of b / a, far inside enter_padded_box's 2^-40."""
    out = t
    if a > wp.float64(0.0):
        out[0] = wp.max(out[0], b * inv_a)
    elif a < wp.float64(0.0):
        out[1] = wp.min(out[1], b * inv_a)
    elif b > wp.float64(0.0):
        out[0] = wp.float64(INF)
    return out


@wp.func
def enter_padded_box(q: TopRay, lo: wp.vec3, hi: wp.vec3, tmin: float, tmax: float) -> float:
    """Entry t of the ray into [lo, hi] widened by s t on every side (walls that move out
    with t: instances.py), clipped to [tmin, tmax], or inf. float64, then widened by
    2^-40 relative: no rounding here can drop a point the bound keeps."""
    t = wp.vec2d(wp.float64(tmin), wp.float64(tmax))
    for k in range(3):
        # o + t d >= lo - s t  and  -(o + t d) >= -(hi + s t)
        t = clip_side(q.rise[k], q.inv_rise[k], wp.float64(lo[k]) - q.o_high[k], t)
        t = clip_side(q.fall[k], q.inv_fall[k], q.o_low[k] - wp.float64(hi[k]), t)
    eps = wp.float64(9.094947e-13)
    t0 = t[0] - eps * wp.abs(t[0])
    if t0 <= t[1] + eps * wp.abs(t[1]):
        return wp.max(float(t0), tmin)
    return INF


@wp.func
def no_instance_hit(out: wp.ref[InstanceHit]):
    out.hit.t = INF
    out.hit.triangle = -1
    out.instance = -1


@wp.func
def instance_hit_distance(h: InstanceHit) -> float:
    return h.hit.t


@wp.func
def keep_instance_hit(h: Hit, inst: int, out: wp.ref[InstanceHit]) -> bool:
    """Keep instance `inst`'s hit in leaf order `h` in `out` if nearer, or as near and of a
    lower instance; True if kept."""
    if h.triangle >= 0 and (h.t < out.hit.t or (h.t == out.hit.t and inst < out.instance)):
        out.hit = h
        out.instance = inst
        return True
    return False


@wp.func
def trace_instances(s: SceneArrays, q: TopRay, first: int, count: int, tmin: float,
                    tmax: float, out: wp.ref[InstanceHit], any_hit: bool) -> bool:
    """A top-level leaf: each instance's own BVH in its object space, with the closest hit
    so far as tmax; True at the first hit of an any-hit query. Hits stay in leaf order
    (`traverse_leaf_order`) until `finish_instance_hit`: the closest unrefined t wins, the
    lower instance at equal t, so the order in which instances are visited (the top
    level's, a packet's: scene/packet.py) does not change which hit is kept."""
    for k in range(first, first + count):
        inst = s.top_ids[k]
        rec = s.instances[inst]
        h = traverse_leaf_order(mesh_view(s.meshes[rec.mesh]),
                                object_ray(rec, q.origin, q.direction), tmin,
                                wp.min(out.hit.t, tmax), any_hit)
        if keep_instance_hit(h, inst, out) and any_hit:
            return True
    return False


@wp.func
def finish_instance_hit(s: SceneArrays, origin: wp.vec3, direction: wp.vec3, tmin: float,
                        tmax: float, out: InstanceHit, any_hit: bool) -> InstanceHit:
    """The kept hit as `traverse` finishes a mesh's (bvh.leaf.finish_traversal), in its
    instance's object space: t refined in float64, the mesh's triangle index."""
    if out.instance >= 0:
        rec = s.instances[out.instance]
        out.hit = finish_traversal(mesh_view(s.meshes[rec.mesh]),
                                   object_ray(rec, origin, direction), tmin, tmax, out.hit,
                                   any_hit)
    return out


@wp.func
def top_result(s: SceneArrays, q: TopRay, tmin: float, tmax: float, out: InstanceHit,
               stopped: bool) -> InstanceHit:
    return finish_instance_hit(s, q.origin, q.direction, tmin, tmax, out, stopped)


# the top level's traversal, from its padded box test and its instance leaves
traverse_top = make_binary_traversal(BinaryTree(
    tree=SceneArrays, query=TopRay, result=InstanceHit, miss=no_instance_hit,
    enter=enter_padded_box, leaf=trace_instances, distance=instance_hit_distance, finish=top_result,
    module=__name__, name="traverse_top"))


@wp.func
def top_walls(s: SceneArrays, q: TopRay, d_low: wp.vec3d, d_high: wp.vec3d,
              largest: wp.float64) -> TopRay:
    """q with the walls' rise and fall for directions within [d_low, d_high] whose largest
    |component| is `largest`."""
    speed = wp.vec3d(wp.float64(s.slope) * largest)
    q.rise = d_high + speed
    q.fall = speed - d_low
    one = wp.vec3d(wp.float64(1.0))
    q.inv_rise = wp.cw_div(one, q.rise)
    q.inv_fall = wp.cw_div(one, q.fall)
    return q


@wp.func
def top_ray(s: SceneArrays, origin: wp.vec3, direction: wp.vec3) -> TopRay:
    """The world ray as the top level tests it."""
    q = TopRay()
    q.origin = origin
    q.direction = direction
    q.o_low = wp.vec3d(origin)
    q.o_high = q.o_low
    d = wp.vec3d(direction)
    return top_walls(s, q, d, d, wp.max(wp.max(wp.abs(d[0]), wp.abs(d[1])), wp.abs(d[2])))


@wp.func
def traverse_scene(s: SceneArrays, origin: wp.vec3, direction: wp.vec3, tmin: float,
                   tmax: float, any_hit: bool) -> InstanceHit:
    """Closest hit over all instances in [tmin, tmax] (or with `any_hit` the first found):
    the top level's binary traversal (bvh.binary_traversal; its depth is at most the
    build's max_depth = STACK_SIZE), each instance's own BVH at its leaves."""
    return traverse_top(s, s.top, top_ray(s, origin, direction), tmin, tmax, any_hit)


@wp.kernel
def scene_trace_kernel(
    s: SceneArrays,
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    tmin: wp.array(dtype=float),  # per ray, or one value for all
    tmax: wp.array(dtype=float),
    find_any: int,
    out_t: wp.array(dtype=float),
    out_triangle: wp.array(dtype=int),
    out_u: wp.array(dtype=float),
    out_v: wp.array(dtype=float),
    out_instance: wp.array(dtype=int),
    invalid: wp.array(dtype=int),  # set to 1 where a ray is one as_rays refuses
    claims: Claims,
):
    items = claimed_items(claims, wp.tid())
    flag_invalid_rays(origins, directions, items[0], items[1], invalid)
    for i in range(items[0], items[1]):
        h = traverse_scene(s, origins[i], directions[i], per_ray(tmin, i), per_ray(tmax, i),
                           find_any != 0)
        out_t[i] = h.hit.t
        out_triangle[i] = h.hit.triangle
        out_u[i] = h.hit.u
        out_v[i] = h.hit.v
        out_instance[i] = h.instance


WARP_MODULES = (scene_trace_kernel.module,)  # this module's kernels (core.launch.load_modules)
