"""Both instruction-set branches of the wide traversal, and the portable one, built in one
process for x86 targets other than the host's (clang's -target-cpu in a module's
`cpu_compiler_flags`, core.compile_options.cpu_target_flags): each says which branch it
compiled (simd_isa, and simd_lanes, which bvh.api's default width follows) and finds the
hits `kernels.trace` finds with the host's build, bit for bit. The host runs every target
up to its own ISA; a target above it is skipped."""

from __future__ import annotations

import functools
import platform
from dataclasses import replace

import numpy as np
import pytest
import warp as wp
from scenesort.kernels.bvh import BvhArrays
from scenesort.kernels.bvh.leaf import finish_traversal
from scenesort.kernels.bvh.wide_traversal import (
    simd_isa,
    simd_lanes,
    simd_support,
    traverse_wide,
)
from scenesort.kernels.core.compile_options import MODULE_OPTIONS, cpu_target_flags
from scenesort.kernels.core.ray import make_ray

from scenesort import kernels

from .test_wide import same_as, tricky_tree

pytestmark = [
    pytest.mark.host_only,
    pytest.mark.skipif(platform.machine().lower() not in ("x86_64", "amd64"),
                       reason="x86 targets (an AArch64 host runs the portable traversal)"),
]

# clang -target-cpu -> the branch of bvh/wide_simd.h it compiles (simd_isa)
TARGETS = {
    "x86-64": 0,  # no AVX2 (AVX and F16C, which Warp adds): traverse_wide_portable
    "x86-64-v3": 1,  # AVX2, FMA (contraction off): traverse_simd
    "x86-64-v4": 2,  # AVX-512VL too: traverse_simd with compressed any-hit pushes
}


@functools.cache
def trace_on(target_cpu: str) -> wp.Kernel:
    """`traverse_wide`, finished as `traverse` finishes it, in a kernel of a Warp module of its
    own, compiled for `target_cpu`."""

    def trace_wide(bvh: BvhArrays, origins: wp.array(dtype=wp.vec3),
                   directions: wp.array(dtype=wp.vec3), tmin: wp.array(dtype=float),
                   tmax: wp.array(dtype=float), any_hit: int, out_t: wp.array(dtype=float, ndim=2),
                   out_triangle: wp.array(dtype=int), isa: wp.array(dtype=int)):
        i = wp.tid()
        if i == 0:
            isa[0] = simd_isa()
            isa[1] = simd_lanes()
        r = make_ray(origins[i], directions[i])
        h = finish_traversal(bvh, r, tmin[i], tmax[i],
                             traverse_wide(bvh, r, tmin[i], tmax[i], any_hit != 0), any_hit != 0)
        out_t[i, 0] = h.t
        out_t[i, 1] = h.u
        out_t[i, 2] = h.v
        out_triangle[i] = h.triangle

    module = f"{__name__}.{target_cpu.replace('-', '_')}"
    kernel = wp.kernel(trace_wide, module=module)
    wp.set_module_options({**MODULE_OPTIONS, "cpu_compiler_flags": cpu_target_flags(target_cpu)},
                          module=module)
    return kernel


def rays_and_trees(shared_scene):
    """(bvh, origins, directions, tmin, tmax) per case: the trees of flat boxes with rays from
    box corners and faces and with zero components (test_wide.tricky_tree), and bunny's
    camera."""
    cases = []
    for width in (4, 8):
        bvh, _, o, d = tricky_tree(width)
        tmax = np.where(np.arange(len(o)) % 2 == 0, 1.0e30,
                        np.random.default_rng(5).random(len(o)) * 2).astype(np.float32)
        cases.append((bvh, o, d, np.zeros(len(o), np.float32), tmax))
    scene = shared_scene("bunny")
    o, d, tmin, tmax = replace(scene.camera, width=96, height=96).rays()
    per_ray = [np.broadcast_to(np.float32(x), len(o)).astype(np.float32) for x in (tmin, tmax)]
    cases.append((kernels.build_bvh(scene.vertices, scene.indices, width=8), o, d, *per_ray))
    return cases


@pytest.mark.parametrize("target_cpu", list(TARGETS))
def test_each_instruction_set_finds_the_hosts_hits(target_cpu, shared_scene):
    host = simd_support("cpu")[1]
    if TARGETS[target_cpu] > host:
        pytest.skip(f"the host does not run {target_cpu}")
    kernel = trace_on(target_cpu)
    isa = wp.zeros(2, dtype=int)
    for bvh, o, d, tmin, tmax in rays_and_trees(shared_scene):
        assert bvh.stats.width in (4, 8)
        for any_hit in (False, True):
            n = len(o)
            out_t = wp.zeros((n, 3), dtype=float)
            out_triangle = wp.zeros(n, dtype=int)
            wp.launch(kernel, dim=n,
                      inputs=[bvh.arrays, wp.array(o, dtype=wp.vec3), wp.array(d, dtype=wp.vec3),
                              wp.array(tmin, dtype=float), wp.array(tmax, dtype=float),
                              int(any_hit), out_t, out_triangle, isa])
            branch, lanes = (int(x) for x in isa.numpy())
            assert branch == TARGETS[target_cpu] and lanes == (8 if branch else 0)
            host_hits = kernels.trace(bvh, o, d, tmin, tmax, any_hit=any_hit)
            t = out_t.numpy()
            got = kernels.Hits(t=t[:, 0], triangle=out_triangle.numpy(), u=t[:, 1], v=t[:, 2])
            assert np.count_nonzero(got.triangle >= 0) > n / 10
            if any_hit:  # the same first hit: lane order on every branch
                assert np.array_equal(got.triangle, host_hits.triangle)
            same_as(got, host_hits)
