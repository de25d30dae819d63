"""A packet's camera rays and occlusion-direction points made by the native CPU code
(film_rays.h) are those of the Warp code that CUDA runs (sample_ray, sample_2d_at), bit
for bit."""

from __future__ import annotations

import numpy as np
import warp as wp
from hypothesis import given, settings
from hypothesis import strategies as st
from scenesort.kernels.core.compile_options import MODULE_OPTIONS
from scenesort.kernels.render.film import filter_table
from scenesort.kernels.render.filtered import FilmCamera, packet_samples_native, sample_ray
from scenesort.kernels.render.sampling import sample_2d_at

wp.set_module_options(MODULE_OPTIONS)

PACKET = 64


@wp.kernel
def native_kernel(cam: FilmCamera, table: wp.array(dtype=float), sampler: int,
                  key: wp.uint32, first: int, count: int, row: int, col: int,
                  origins: wp.array(dtype=wp.vec3), directions: wp.array(dtype=wp.vec3),
                  tmin: wp.array(dtype=float), tmax: wp.array(dtype=float),
                  points: wp.array(dtype=wp.vec2), made: wp.array(dtype=int)):
    made[0] = packet_samples_native(cam.rotation, cam.position, cam.centre, cam.step,
                                    cam.offset, cam.persp, cam.aperture, cam.clip_start,
                                    cam.clip_end, sampler, table, key, first, count, row, col,
                                    origins, directions, tmin, tmax, points, 0)


@wp.kernel
def warp_kernel(cam: FilmCamera, table: wp.array(dtype=float), sampler: int, key: wp.uint32,
                first: int, row: int, col: int, out: wp.array2d(dtype=float)):
    m = wp.tid()
    o, d, t0, t1 = sample_ray(cam, table, sampler, key, first + m, row, col)
    u = sample_2d_at(sampler, key, wp.uint32(first + m))
    for a in range(3):
        out[m, a] = o[a]
        out[m, 3 + a] = d[a]
    out[m, 6] = t0
    out[m, 7] = t1
    out[m, 8] = u[0]
    out[m, 9] = u[1]


def run_both(cam: FilmCamera, table: wp.array, sampler: int, key: int, first: int,
             count: int, row: int, col: int) -> tuple[int, np.ndarray, np.ndarray]:
    """The native code's (made, its rays and points) and the Warp code's, on the CPU."""
    with wp.ScopedDevice("cpu"):
        return _run_both(cam, table, sampler, key, first, count, row, col)


def _run_both(cam: FilmCamera, table: wp.array, sampler: int, key: int, first: int,
              count: int, row: int, col: int) -> tuple[int, np.ndarray, np.ndarray]:
    origins, directions = (wp.zeros(PACKET, dtype=wp.vec3) for _ in range(2))
    tmin, tmax = (wp.zeros(PACKET, dtype=float) for _ in range(2))
    points = wp.zeros(PACKET, dtype=wp.vec2)
    made = wp.zeros(1, dtype=int)
    expected = wp.zeros((PACKET, 10), dtype=float)
    wp.launch(native_kernel, dim=1, inputs=[cam, table, sampler, key, first, count, row, col,
                                            origins, directions, tmin, tmax, points, made])
    wp.launch(warp_kernel, dim=count, inputs=[cam, table, sampler, key, first, row, col,
                                              expected])
    got = np.concatenate([origins.numpy(), directions.numpy(), tmin.numpy()[:, None],
                          tmax.numpy()[:, None], points.numpy()], axis=1)[:count]
    return int(made.numpy()[0]), got, expected.numpy()[:count]


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1),
       kind=st.sampled_from([("BLACKMAN_HARRIS", 1.5), ("GAUSSIAN", 1.5), ("BOX", 1.0)]),
       camera=st.sampled_from(["pinhole", "ortho", "lens"]),
       sampler=st.sampled_from([0, 1]), key=st.integers(0, 2**32 - 1),
       first=st.integers(0, 2**31 - 1 - PACKET), count=st.integers(1, PACKET),
       pixel=st.tuples(st.integers(0, 4095), st.integers(0, 4095)))
def test_native_and_warp_samples_agree(seed, kind, camera, sampler, key, first, count, pixel):
    """Cameras of random numbers (a rotation need not be one: every product and sum rounds),
    either sampler, any pixel key and sample range; the native rays only for a pinhole
    PERSP camera, the points always."""
    rng = np.random.default_rng(seed)
    cam = FilmCamera()
    cam.rotation = wp.mat33(*rng.normal(size=9))
    cam.position = wp.vec3(*rng.normal(scale=10.0, size=3))
    cam.centre = wp.vec2(*rng.uniform(0.0, 4096.0, 2))
    cam.step = wp.vec2(*rng.uniform(-1.0, 1.0, 2) / rng.uniform(100.0, 4096.0))
    cam.offset = wp.vec2(*rng.normal(scale=0.1, size=2))
    cam.persp = 0 if camera == "ortho" else 1
    cam.clip_start, cam.clip_end = rng.uniform(1e-3, 1.0), rng.uniform(1.0, 1e4)
    cam.aperture = 0.1 if camera == "lens" else 0.0
    cam.focus, cam.blades, cam.blade_rotation, cam.inv_ratio = 2.0, 0, 0.0, 1.0
    table = wp.array(filter_table(*kind), dtype=float, device="cpu")
    made, got, expected = run_both(cam, table, sampler, key, first, count, *pixel)
    assert made == (1 if camera == "pinhole" else 0)
    np.testing.assert_array_equal(got[:, 8:].view(np.uint32), expected[:, 8:].view(np.uint32))
    if made:
        np.testing.assert_array_equal(got[:, :8].view(np.uint32),
                                      expected[:, :8].view(np.uint32))
    else:  # the rays untouched
        assert not got[:, :8].any()
