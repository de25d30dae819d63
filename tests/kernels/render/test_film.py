"""The Film's pixel filter (kernels/render/film.py): Cycles' inverted-CDF table and the
sub-pixel positions drawn from it, checked against the filter's own normalised profile."""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np
import pytest
import warp as wp
from scenesort.backend.render.scenes import shared_scene
from scenesort.kernels.bvh.packet import PACKET
from scenesort.kernels.render import filtered
from scenesort.kernels.render.camera import Camera
from scenesort.kernels.render.film import (
    FILTER_TABLE_SIZE,
    filter_position,
    filter_profile,
    filter_table,
)
from scenesort.kernels.render.filtered import FilmCamera, camera_ray, device_camera, render_film
from scenesort.kernels.render.primary import scene_shading
from scenesort.kernels.render.sampling import SAMPLERS, pixel_key, sample_2d_at
from scenesort.kernels.render.surface import occlusion_origin
from scenesort.kernels.render.tracers import (
    MeshTracer,
    PacketRays,
    packet_hit_surface,
    packet_occlusion_origin,
    packet_rays,
    scene_mesh,
)

from scenesort import kernels
from scenesort.ao_options import PIXEL_FILTERS

PIXELS = 256
SAMPLES = 256  # a power of two: each pixel's Sobol points are a complete net


@wp.kernel
def _positions(
    table: wp.array(dtype=float), sampler: int, seed: int, out: wp.array2d(dtype=wp.vec2)
):
    pixel, index = wp.tid()
    out[pixel, index] = filter_position(table, sampler, pixel_key(pixel, seed), index)


def positions(kind: str, width: float, sampler: str, device: str) -> np.ndarray:
    """(PIXELS, SAMPLES, 2) offsets from the pixel centre, in pixels."""
    table = wp.array(filter_table(kind, width), dtype=float, device=device)
    out = wp.empty((PIXELS, SAMPLES), dtype=wp.vec2, device=device)
    wp.launch(_positions, dim=out.shape, inputs=[table, SAMPLERS[sampler], 7, out], device=device)
    return out.numpy() - 0.5


def profile_probabilities(kind: str, width: float, edges: np.ndarray) -> np.ndarray:
    """The filter's probability per bin: its profile integrated finely, normalised."""
    fine = np.linspace(edges[0], edges[-1], 200 * (edges.size - 1) + 1)
    mass = np.diff(np.concatenate(([0.0], np.cumsum(filter_profile(kind, width, fine)))))
    mass = np.add.reduceat(mass[1:], np.arange(0, fine.size - 1, 200))
    return mass / mass.sum()


FILTERS = [("BLACKMAN_HARRIS", 1.5), ("GAUSSIAN", 1.5), ("BOX", 1.0), ("BOX", 2.5)]


def support(kind: str, width: float) -> float:
    """Half the span of the table's offsets (film.py): w / 2."""
    return {"BOX": 0.5, "GAUSSIAN": 1.5, "BLACKMAN_HARRIS": 1.0}[kind] * width


def table_probabilities(kind: str, width: float, edges: np.ndarray) -> np.ndarray:
    """The probability per bin of the table read with linear interpolation at uniform u."""
    table = filter_table(kind, width).astype(np.float64) - 0.5
    return np.diff(np.interp(edges, table, np.linspace(0.0, 1.0, FILTER_TABLE_SIZE)))


@pytest.mark.host_only
@pytest.mark.parametrize(("kind", "width"), FILTERS)
def test_table_distribution_is_the_normalised_profile(kind, width):
    """The table's distribution differs from the filter's profile by no more than its
    resolution: total variation under 3/1023 (Cycles' table spreads its last 1/1023 of u
    linearly over the tails, where Blackman-Harris and the Gaussian have almost no mass)."""
    edges = np.linspace(-support(kind, width), support(kind, width), 25)
    p_table = table_probabilities(kind, width, edges)
    p_profile = profile_probabilities(kind, width, edges)
    assert 0.5 * np.abs(p_table - p_profile).sum() < 3.0 / 1023
    assert np.sum(p_table) == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize(("kind", "width"), FILTERS)
@pytest.mark.parametrize("sampler", ["sobol", "random"])
def test_offsets_follow_the_table(kind, width, sampler, device):
    """Histograms of the x and y offsets drawn on the device match the table's distribution
    within 4 binomial sigmas per bin (and so the profile, by the test above)."""
    xy = positions(kind, width, sampler, device)
    s = support(kind, width)
    edges = np.linspace(-s, s, 25)
    p = table_probabilities(kind, width, edges)
    n = PIXELS * SAMPLES
    sigma = np.sqrt(n * p * (1 - p)) + 1.0
    for axis in (0, 1):
        v = xy[..., axis].ravel()
        assert np.all(np.abs(v) <= s + 1e-5)
        counts, _ = np.histogram(v, bins=edges)
        z = (counts - n * p) / sigma
        assert np.max(np.abs(z)) < 4.0, (axis, np.round(z, 1))


def test_gaussian_is_cycles_sigma_of_a_quarter_width(device):
    """Cycles' Gaussian of width 1.5 px is exp(-2 (6v / 4.5)^2): sigma 0.375 px. Checked by
    the median of |offset| (0.6745 sigma), which the table's thin tails cannot move."""
    xy = positions("GAUSSIAN", 1.5, "sobol", device)
    assert np.median(np.abs(xy)) == pytest.approx(0.6744898 * 0.375, rel=0.01)
    assert np.mean(xy) == pytest.approx(0.0, abs=0.003)


def test_sobol_positions_are_stratified(device):
    """With Owen-scrambled Sobol, every pixel's 256 positions put exactly 16 in each of 16
    equal-probability bins of x: the filter's inverse CDF keeps the strata of u."""
    table = filter_table("BLACKMAN_HARRIS", 1.5)
    xy = positions("BLACKMAN_HARRIS", 1.5, "sobol", device) + 0.5
    quantiles = np.interp(np.linspace(0, 1, 17), np.linspace(0, 1, FILTER_TABLE_SIZE), table)
    for pixel in xy[:16]:
        counts, _ = np.histogram(pixel[:, 0], bins=quantiles)
        assert np.all(np.abs(counts - 16) <= 1), counts  # +-1: table interpolation at a bin edge


@wp.kernel
def _strata(table: wp.array(dtype=float), seed: int, out: wp.array2d(dtype=int)):
    pixel, index = wp.tid()
    key = pixel_key(pixel, seed)
    right = filter_position(table, 1, key, index)[0] > 0.5
    # the occlusion direction's first coordinate
    upper = sample_2d_at(1, key, wp.uint32(index))[0] >= 0.5
    out[pixel, index] = wp.where(right == upper, 1, 0)


def test_filter_and_occlusion_strata_are_independent(device):
    """Regression: with the filter's Sobol index unshuffled, sample i's sub-pixel half and
    its occlusion direction's half agreed for all or none of a pixel's samples, which left
    each filtered pixel a bias (RMSE against Cycles stuck at 0.027 from 64 to 256 spp).
    Now they agree for about half of each pixel's samples."""
    table = wp.array(filter_table("BOX", 1.0), dtype=float, device=device)
    out = wp.empty((PIXELS, SAMPLES), dtype=int, device=device)
    wp.launch(_strata, dim=out.shape, inputs=[table, 3, out], device=device)
    agree = out.numpy().mean(axis=1)
    assert np.all((agree > 0.3) & (agree < 0.7)), np.sort(agree)[[0, -1]]


@pytest.mark.host_only
@pytest.mark.parametrize("kind", PIXEL_FILTERS)
def test_table_is_monotone_and_symmetric(kind):
    t = filter_table(kind, 1.5).astype(np.float64)
    assert np.all(np.diff(t) >= 0.0)
    np.testing.assert_allclose(t[:1023] + t[1022::-1], 1.0, atol=1e-6)
    assert t[511] == pytest.approx(0.5)


@pytest.mark.host_only
@pytest.mark.parametrize(
    ("kind", "width", "field"),
    [("MITCHELL", 1.5, "pixel_filter"), ("BOX", 0.0, "filter_width"),
     ("BOX", float("nan"), "filter_width"), ("GAUSSIAN", 11.0, "filter_width")],
)
def test_bad_filter_names_the_field(kind, width, field):
    with pytest.raises(ValueError, match=field):
        filter_table(kind, width)


def half_plane(edge_x: float) -> kernels.Bvh:
    """The plane z = 0 over x < edge_x (world units), facing +z."""
    v = np.array([[-100, -100, 0], [edge_x, -100, 0], [edge_x, 100, 0], [-100, 100, 0]],
                 dtype=np.float32)
    return kernels.build_bvh(v, np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32))


def ortho_camera(width: int, height: int) -> Camera:
    """Looking down -z from z = 5, one world unit per pixel: raster x = world x + width / 2."""
    m = np.eye(4)
    m[2, 3] = 5.0
    return Camera(matrix_world=m, width=width, height=height, type="ORTHO",
                  ortho_scale=float(width))


@pytest.mark.parametrize(("kind", "width"), [("BLACKMAN_HARRIS", 1.5), ("GAUSSIAN", 1.5),
                                             ("BOX", 1.0)])
def test_edge_alpha_is_the_filtered_coverage(kind, width):
    """A straight silhouette between two pixel centres: each pixel's alpha is the filter's
    mass left of the edge (brute force from the table), within 4 binomial sigmas; the open
    plane's AO is exactly 1 and pixels beyond the filter's reach are exactly 0 or 1. The
    Normal pass is the plane's normal times the alpha (the hits' normals over all samples,
    as Cycles'), exactly."""
    w, h, spp = 16, 4, 256
    edge = 7.3  # raster x of the edge
    r = render_film(half_plane(edge - w / 2), ortho_camera(w, h), spp=spp,
                    pixel_filter=kind, filter_width=width)
    table = filter_table(kind, width).astype(np.float64)
    expected = np.interp(edge - np.arange(w), table, np.linspace(0.0, 1.0, FILTER_TABLE_SIZE))
    sigma = np.sqrt(expected * (1 - expected) / spp) + 1.0 / spp
    assert np.all(np.abs(r.alpha - expected) <= 4 * sigma), (r.alpha[0], expected)
    exact = (expected == 0.0) | (expected == 1.0)
    assert np.array_equal(r.alpha[:, exact], np.broadcast_to(expected[exact], (h, exact.sum())))
    assert exact.sum() >= w - 6  # the widest (Gaussian 1.5: +-2.25 px) reaches 5 pixels
    assert np.all(r.ao == 1.0)
    assert np.array_equal(r.normals[..., 2], r.alpha) and not r.normals[..., :2].any()


def test_width_zero_is_the_pixel_centre_render(shared_scene):
    """filter_width=0 is render_ao over Camera.rays(), bit for bit, alpha its hit mask,
    the normals its hits' normals."""
    scene = shared_scene("sponza")
    cam = Camera.look_at((-13.0, 2.5, 0.0), (10.0, 4.5, 0.0), (0, 1, 0), 60.0, 24, 16)
    bvh = kernels.build_bvh(scene.vertices, scene.indices)
    film = render_film(bvh, cam, spp=8, filter_width=0)
    o, d, t0, t1 = cam.rays()
    ref = kernels.render_ao(bvh, o, d, spp=8, tmin=t0, tmax=t1)
    assert np.array_equal(film.ao.ravel(), ref.ao)
    assert np.array_equal(film.alpha.ravel(), (ref.spp_used > 0).astype(np.float32))
    assert np.array_equal(film.normals.reshape(-1, 3), ref.normals)


def test_filtered_render_does_not_depend_on_threads(shared_scene):
    """96x64 pixels at 8 spp: 12 parts of pixels, run by 1 or 2 host threads."""
    scene = shared_scene("sponza")
    cam = Camera.look_at((-13.0, 2.5, 0.0), (10.0, 4.5, 0.0), (0, 1, 0), 60.0, 96, 64)
    bvh = kernels.build_bvh(scene.vertices, scene.indices)
    a = render_film(bvh, cam, spp=8, threads=1, filter_width=1.5)
    b = render_film(bvh, cam, spp=8, threads=2, filter_width=1.5)
    assert np.array_equal(a.ao, b.ao) and np.array_equal(a.alpha, b.alpha)
    assert np.array_equal(a.normals, b.normals)


def test_filtered_normals_are_over_each_pixels_own_samples(shared_scene):
    """With an error target (pixels at different sample counts) the Normal pass is each
    pixel's mean over its own samples: no longer than its alpha (a mean of unit normals
    over hits, misses 0), the same as with 256 samples everywhere but for sampling noise,
    and in most pixels the pixel centre's normal."""
    sc = shared_scene("conference")
    bvh = kernels.build_bvh(sc.vertices, sc.indices)
    cam = type(sc.camera).from_dict({**sc.camera.to_dict(), "width": 48, "height": 36})
    r = render_film(bvh, cam, spp=16, target_error=0.02, max_spp=256, filter_width=1.5)
    assert r.spp_used.max() > r.spp_used.min()
    length = np.linalg.norm(r.normals, axis=-1)
    assert np.all(length <= r.alpha + 1e-5) and length.mean() > 0.8
    fixed = render_film(bvh, cam, spp=256, filter_width=1.5).normals
    assert np.abs(r.normals - fixed).max() < 0.1  # 16 spp: 0.0156 seen
    centre = render_film(bvh, cam, spp=1, filter_width=0).normals
    assert np.median(np.sum(r.normals * centre, axis=-1)) > 0.99


def test_tile_order_is_every_pixel_tile_by_tile():
    """40x24 pixels in 16x16 tiles: 3 x 2 tiles, those at the right and bottom edges cut."""
    order = filtered.tile_order(40, 24)
    assert np.array_equal(np.sort(order), np.arange(40 * 24))
    row, col = np.divmod(order, 40)
    tile = (row // filtered.TILE) * 3 + col // filtered.TILE
    assert np.array_equal(tile, np.sort(tile))  # each tile's pixels in one run, in tile order
    sizes = np.bincount(tile)
    assert sizes.tolist() == [256, 256, 128, 128, 128, 64]
    first = order[:filtered.TILE]  # the first tile's top row, left to right
    assert np.array_equal(first, np.arange(filtered.TILE))


@pytest.mark.parametrize("settings", [{"spp": 8}, {"target_error": 0.05, "spp": 1}])
def test_tile_order_renders_the_row_order_image(shared_scene, monkeypatch, settings):
    """The kernels get pixels tile by tile (the cache's sake); each pixel's samples are its
    own, so the image, fixed or adaptive, is the one the rows give."""
    scene = shared_scene("sponza")
    cam = Camera.look_at((-13.0, 2.5, 0.0), (10.0, 4.5, 0.0), (0, 1, 0), 60.0, 52, 36)
    bvh = kernels.build_bvh(scene.vertices, scene.indices)
    film = {"filter_width": 1.5, **settings}
    tiles = render_film(bvh, cam, **film)
    monkeypatch.setattr(filtered, "tile_order", lambda width, height: np.arange(width * height))
    rows = render_film(bvh, cam, **film)
    for field in ("ao", "alpha", "spp_used"):
        assert np.array_equal(getattr(tiles, field), getattr(rows, field)), field


@pytest.mark.parametrize(("settings", "field"), [
    ({"engine": "dacrt", "filter_width": 1.5}, "dacrt"),
    ({"denoise": True, "filter_width": 1.5}, "denoise"),
    ({"pixel_filter": "MITCHELL"}, "pixel_filter"), ({"filter_width": -1.0}, "filter_width"),
    ({"filter_width": 10.5}, "filter_width")])
def test_bad_film_arguments_name_the_field(settings, field):
    with pytest.raises(ValueError, match=field):
        render_film(half_plane(0.0), ortho_camera(4, 4), **settings)


def test_progress_is_called_between_rounds_and_cancels():
    """A filtered render reports its rounds (monotone, ending at 1) and stops when the
    progress callback raises: the service's cancellation point."""
    seen = []
    render_film(half_plane(0.0), ortho_camera(64, 64), spp=1024, filter_width=1.5,
                progress=lambda f, phase: seen.append((f, phase)))
    fractions = [f for f, _ in seen]
    assert len(seen) >= 3 and fractions == sorted(fractions) and seen[-1] == (1.0, "done")

    class Stop(Exception):
        pass

    def stop(fraction: float, phase: str) -> None:
        if fraction > 0.0:
            raise Stop

    with pytest.raises(Stop):
        render_film(half_plane(0.0), ortho_camera(64, 64), spp=1024, filter_width=1.5,
                    progress=stop)


def test_two_level_scene_renders_as_its_mesh():
    """The same half plane as a mesh and as a two-level scene's one instance (the
    identity): the same filtered coverage and AO, sample for sample."""
    w, h = 16, 4
    bvh = half_plane(7.3 - w / 2)
    scene = kernels.build_scene([bvh], np.array([0]), np.eye(4, dtype=np.float32)[None, :3])
    a = render_film(bvh, ortho_camera(w, h), spp=64, filter_width=1.5)
    b = render_film(scene, ortho_camera(w, h), spp=64, filter_width=1.5)
    assert np.array_equal(a.alpha, b.alpha) and np.array_equal(a.ao, b.ao)
    assert 0.0 < a.alpha[0, 7] < 1.0


@pytest.mark.parametrize("name", ["conference", "bunny"])
def test_camera_packets_render_as_single_rays(name):
    """A filtered render traces each pixel's camera rays as packets on an AVX2 CPU, a mesh's
    through bvh/packet.py, a two-level scene's through scene/packet.py (tests/kernels/scene/
    test_scene_packets.py: its rays ray by ray): on the mesh and on a scene of it as its one
    instance, the same image, sample for sample."""
    sc = shared_scene(name)
    bvh = kernels.build_bvh(sc.vertices, sc.indices)
    scene = kernels.build_scene([bvh], np.array([0]), np.eye(4, dtype=np.float32)[None, :3])
    cam = type(sc.camera).from_dict({**sc.camera.to_dict(), "width": 48, "height": 36})
    a = render_film(bvh, cam, spp=80, filter_width=1.5)
    b = render_film(scene, cam, spp=80, filter_width=1.5)
    assert np.array_equal(a.alpha, b.alpha) and np.array_equal(a.ao, b.ao)
    assert np.array_equal(a.normals, b.normals)
    assert a.alpha.mean() > 0.1


@wp.kernel
def _deferred_origins(tracer: Any, shading: Any, rays: PacketRays,
                      directions: wp.array2d(dtype=wp.vec3), out: wp.array2d(dtype=wp.vec3),
                      lifted_out: wp.array2d(dtype=int)):
    k, j = wp.tid()
    unlifted, hit = packet_hit_surface(tracer, shading, rays, k, False)
    lifted, hit_again = packet_hit_surface(tracer, shading, rays, k, True)
    if hit:
        w = directions[k, j]
        if wp.dot(w, lifted.n) < 0.0:
            w = -w
        eager = occlusion_origin(lifted, w)
        out[k, 2 * j] = eager
        out[k, 2 * j + 1] = packet_occlusion_origin(tracer, shading, rays, k, unlifted, w)
        lifted_out[k, j] = wp.where(eager == lifted.point, 0, 1)


def test_a_packet_surfaces_lift_is_made_where_it_moves_the_origin():
    """The film's camera packets leave a surface's terminator lift out and make the surface
    again, lifted, only where the occlusion direction is near the terminator
    (tracers.packet_occlusion_origin): every origin equals the one from the surface made
    with its lift, on a mesh and through a two-level scene, with bent corner normals and
    Cycles' terminator offset, for directions all over the hemisphere (some lifted)."""
    sc = shared_scene("bunny")
    v, f = sc.vertices, sc.indices
    rng = np.random.default_rng(4)
    ng = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    ng /= np.linalg.norm(ng, axis=1, keepdims=True)
    normals = (ng[:, None, :] + rng.normal(0.0, 0.3, (len(f), 3, 3))).astype(np.float32)
    bvh = kernels.build_bvh(v, f)
    scene = kernels.build_scene([bvh], np.array([0]), np.eye(4, dtype=np.float32)[None, :3])
    cam = type(sc.camera).from_dict({**sc.camera.to_dict(), "width": 24, "height": 18})
    o, d, _, _ = cam.rays()
    hits = kernels.trace(bvh, o, d)
    n, per = len(o), 64
    w = rng.normal(size=(n, per, 3)).astype(np.float32)
    w /= np.linalg.norm(w, axis=2, keepdims=True)
    mesh_tracer = MeshTracer()
    mesh_tracer.bvh = bvh.arrays
    mesh_tracer.vertices, mesh_tracer.indices = scene_mesh(bvh).v, scene_mesh(bvh).f
    for tracer, shading, two_level in (
            (mesh_tracer, scene_shading(bvh, normals, 0.2), False),
            (scene.arrays, scene_shading(scene, [normals], 0.2), True)):
        rays = packet_rays(-(-n // PACKET), two_level, wp.get_device("cpu"))
        for name, x in (("directions", d), ("t", hits.t), ("triangle", hits.triangle),
                        ("u", hits.u), ("v", hits.v),
                        ("instance", np.where(hits.triangle >= 0, 0, -1).astype(np.int32))):
            getattr(rays, name)[:n].assign(x)
        out = wp.zeros((n, 2 * per), dtype=wp.vec3)
        lifted = wp.zeros((n, per), dtype=int)
        wp.launch(_deferred_origins, dim=(n, per), inputs=[
            tracer, shading, rays, wp.array(w, dtype=wp.vec3), out, lifted])
        origins = out.numpy()
        assert np.array_equal(origins[:, 0::2], origins[:, 1::2])
        assert 0.005 < lifted.numpy()[hits.triangle >= 0].mean() < 0.9


@wp.kernel
def _centre_rays(cam: FilmCamera, width: int, out: wp.array2d(dtype=float)):
    k = wp.tid()
    row = k / width
    o, d, t0, t1 = camera_ray(cam, float(k - row * width) + 0.5, float(row) + 0.5,
                              wp.vec2(0.5, 0.5))
    for j in range(3):
        out[k, j] = o[j]
        out[k, 3 + j] = d[j]
    out[k, 6] = t0
    out[k, 7] = t1


FRAMINGS = [  # backend/render/framing.py: a window of the frame, non-square pixels
    ({"x": 3, "y": 5, "width": 7, "height": 9}, (1.0, 1.0)),
    (None, (1.0, 2.0)),
    ({"x": 0, "y": 4, "width": 12, "height": 10}, (3.0, 1.0)),
]


@pytest.mark.parametrize("framing", [None, *FRAMINGS])
@pytest.mark.parametrize("settings", [
    {"type": "PERSP", "lens": 35.0, "sensor_fit": "AUTO", "shift_x": 0.1, "clip_start": 0.5},
    {"type": "PERSP", "sensor_fit": "VERTICAL", "shift_y": -0.2, "clip_end": 50.0},
    {"type": "ORTHO", "ortho_scale": 4.0, "sensor_fit": "HORIZONTAL", "shift_x": -0.3},
])
def test_device_camera_is_the_camera_model(settings, framing, device):
    """The kernel's camera ray through each pixel centre is Camera.rays()'s (float32), also
    for the service's framed cameras (a window, non-square pixels): what a filtered job
    renders is the frame's part the pixel-centre job renders."""
    angle = 0.3
    m = np.eye(4)
    m[:3, :3] = [[math.cos(angle), 0, math.sin(angle)], [0, 1, 0],
                 [-math.sin(angle), 0, math.cos(angle)]]
    m[:3, 3] = (1.0, -2.0, 3.0)
    cam = Camera(matrix_world=m, width=12, height=20, **settings)
    if framing is not None:
        from scenesort.backend.render.framing import framed

        cam = framed(cam.to_dict(), *framing)
    out = wp.empty((cam.width * cam.height, 8), dtype=float, device=device)
    wp.launch(_centre_rays, dim=out.shape[0], inputs=[device_camera(cam), cam.width, out],
              device=device)
    got = out.numpy()
    for i, ref in enumerate(cam.rays()):
        ref = np.asarray(ref, dtype=np.float64).reshape(len(got), -1)
        cols = slice(3 * i, 3 * i + 3) if i < 2 else slice(4 + i, 5 + i)
        np.testing.assert_allclose(got[:, cols], ref, rtol=1e-5, atol=1e-5)


@functools.cache
def bunny_reference() -> tuple:
    """The bunny at 160x120, its BVH and an 8192-spp render through Blackman-Harris 1.5 px
    (made once per session: 30 s on 2 cores)."""
    scene = shared_scene("bunny", 160, 120)
    bvh = kernels.build_bvh(scene.vertices, scene.indices)
    ref = render_film(bvh, scene.camera, spp=8192, seed=999, pixel_filter="BLACKMAN_HARRIS",
                      filter_width=1.5)
    return scene, bvh, ref


@pytest.mark.slow
@pytest.mark.parametrize("target", [0.05, 0.02])
def test_error_target_holds_on_filtered_pixels(target):
    """target_error through the filter (the bunny's silhouette against the sky at
    160x120: 3276 covered pixels, 867 of them edges): the adaptive rounds run over the
    covered pixels with the edges' variance in their statistics. Over 8 seeds the achieved
    RMSE (against an 8192-spp filtered reference, its own estimated error subtracted) lies
    in [0.7, 1.0] x the target (issue 32's calibration band) and the estimate within 25%
    of it. Measured: 0.81-0.92x at 0.05, 0.79-0.90x at 0.02; estimates 0.81-1.01. (At
    64x48, 634 covered pixels, the band does not hold: 0.58-0.99x, never above 1.)"""
    scene, bvh, ref = bunny_reference()
    film = {"pixel_filter": "BLACKMAN_HARRIS", "filter_width": 1.5}
    covered = ref.alpha > 0
    for seed in range(8):
        r = render_film(bvh, scene.camera, spp=1, seed=seed, target_error=target, **film)
        mse = np.mean((r.ao[covered].astype(np.float64) - ref.ao[covered]) ** 2)
        achieved = math.sqrt(max(mse - ref.rmse_estimate**2, 0.0))
        assert 0.7 * target <= achieved <= target, (seed, achieved / target)
        assert abs(r.rmse_estimate / achieved - 1.0) <= 0.25, (seed, r.rmse_estimate, achieved)
        assert r.spp_mean >= 8  # at least the minimum, on the covered pixels


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["interior", "thin", "corner", "dof"])
def test_error_target_holds_on_every_scene_kind(kind):
    """Issue 32's calibration on the generated kinds (benchmarks/scene_kinds.py) where the
    shared meshes say nothing: a closed interior seen from inside (no sky), grass and
    wires against the sky (edges everywhere), the built-in room corner open to the sky and
    the same with depth of field. At 160x120, target 0.02, two seeds each: the achieved
    RMSE (against a 4096-spp reference, its own estimated error subtracted) in [0.7, 1.0]
    x the target. benchmarks/film_cost.py measures the same over 3 seeds, 3 targets and 2
    sizes (docs/benchmarks.md)."""
    from benchmarks.scene_kinds import scene_kind

    target, film = 0.02, {"pixel_filter": "BLACKMAN_HARRIS", "filter_width": 1.5}
    scene = scene_kind(kind, 160, 120)
    bvh = kernels.build_bvh(scene.vertices, scene.indices)
    ref = render_film(bvh, scene.camera, spp=4096, seed=999, **film)
    covered = ref.alpha > 0
    for seed in (1, 2):
        r = render_film(bvh, scene.camera, spp=1, seed=seed, target_error=target, **film)
        mse = np.mean((r.ao[covered].astype(np.float64) - ref.ao[covered]) ** 2)
        achieved = math.sqrt(max(mse - ref.rmse_estimate**2, 0.0))
        assert 0.7 * target <= achieved <= target, (seed, achieved / target)


def disk_cdf(t: np.ndarray, radius: float) -> np.ndarray:
    """P(x < t) for x the first coordinate of a uniform point of a disk of `radius`."""
    r = np.clip(t / radius, -1.0, 1.0)
    return 0.5 + (r * np.sqrt(1.0 - r * r) + np.arcsin(r)) / math.pi


@pytest.mark.parametrize(("kind", "focus", "ratio"), [
    ("PERSP", 5.0, 1.0), ("PERSP", 2.5, 1.0), ("PERSP", 10.0, 0.5),
    ("ORTHO", 5.0, 1.0), ("ORTHO", 2.5, 1.0), ("ORTHO", 10.0, 0.5)])
def test_depth_of_field_blurs_an_edge_by_its_circle_of_confusion(kind, focus, ratio):
    """A half plane's straight edge 5 units below a lens of radius 0.3 (Box filter 1 px):
    a ray from lens point L through the point in focus meets the plane at x_p + L_x (1 -
    Z / F) (x_p: where the pinhole's ray meets it: Z times the raster point at depth 1
    for PERSP, the raster point itself for ORTHO, Cycles' camera_sample_orthographic), so
    each pixel's alpha is the pixel's mean of the lens's x marginal (a disk's, squeezed by
    `aperture_ratio`) beyond the edge, integrated here by quadrature: within 4 binomial
    sigmas at 1024 spp. In focus (F = Z) the edge is as sharp as a pinhole's."""
    w, h, spp, z, radius, edge = 16, 4, 1024, 5.0, 0.3, 0.1
    m = np.eye(4)
    m[2, 3] = z
    cam = Camera(matrix_world=m, width=w, height=h, sensor_fit="HORIZONTAL", type=kind,
                 ortho_scale=3.0, aperture_size=radius, focus_distance=focus,
                 aperture_ratio=ratio)
    r = render_film(half_plane(edge), cam, spp=spp, pixel_filter="BOX", filter_width=1.0)
    pix = (cam.plane_scale() if kind == "PERSP" else cam.ortho_scale) / w
    u = (np.arange(4000) + 0.5) / 4000
    x_p = (np.arange(w)[:, None] + u[None, :] - w / 2) * pix  # (pixel, position)
    k = abs(1.0 - z / focus)  # the lens offset's scale at the plane
    gap = edge - (z if kind == "PERSP" else 1.0) * x_p
    sharp = (gap > 0).mean(axis=1)  # a pinhole's
    expected = sharp if k == 0.0 else disk_cdf(gap / k, radius / ratio).mean(axis=1)
    sigma = np.sqrt(expected * (1 - expected) / spp) + 1.0 / spp
    assert np.all(np.abs(r.alpha[0] - expected) <= 4 * sigma), (r.alpha[0], expected)
    assert k == 0.0 or np.abs(expected - sharp).max() > 0.1  # the test sees the blur


def test_occluders_occlude_unseen():
    """Ray visibility: occlusion rays go through `occluders`, camera rays through `bvh`.
    A lid just above the floor, only among the occluders, darkens the floor under it to 0
    and leaves alpha (the camera's) as the floor alone gives it."""
    w, h = 16, 4
    floor = half_plane(100.0)
    lid = np.array([[-100, -100, 0.01], [100, -100, 0.01], [100, 100, 0.01],
                    [-100, 100, 0.01]], np.float32)
    lid_bvh = kernels.build_bvh(lid, np.array([[0, 2, 1], [0, 3, 2]], np.int32))
    one = np.eye(4, dtype=np.float32)[None, :3]
    seen = kernels.build_scene([floor], np.array([0]), one)
    both = kernels.build_scene([floor, lid_bvh], np.array([0, 1]), np.concatenate([one, one]))
    film = {"spp": 16, "distance": 0.5, "filter_width": 1.5}
    alone = render_film(seen, ortho_camera(w, h), **film)
    lidded = render_film(seen, ortho_camera(w, h), occluders=both, **film)
    assert np.array_equal(lidded.alpha, alone.alpha) and np.all(alone.alpha == 1.0)
    assert np.all(alone.ao == 1.0) and np.all(lidded.ao == 0.0)
    with pytest.raises(ValueError, match="occluders"):
        render_film(floor, ortho_camera(w, h), occluders=both, **film)


def _lifted(bvh: kernels.Bvh, z: float) -> kernels.Scene:
    """`bvh` as a two-level scene's one instance, moved up by z."""
    m = np.eye(4, dtype=np.float32)[None, :3].copy()
    m[0, 2, 3] = z
    return kernels.build_scene([bvh], np.array([0]), m)


@pytest.mark.parametrize("kind", ["ORTHO", "PERSP"])
def test_a_holdout_hides_what_is_behind_it_sample_by_sample(kind):
    """Holdout (Cycles: alpha 0 and AO 0 where it covers): a card over the floor's left
    half, only in `holdout`. Each sample meets the floor or, first, the card, so coverage
    and the held fraction add up to 1 in every pixel; the held samples count as misses (AO
    1: the AO pass subtracts them as it does the sky); pixels under the card are held
    whole, and pixels beyond the filter's reach of its edge are the render without a
    holdout, bit for bit. The PERSP camera's rays are made natively (film_rays.h), the
    ORTHO camera's by the Warp code."""
    w, h = 16, 4
    floor = _lifted(half_plane(100.0), 0.0)
    card = _lifted(half_plane(0.0), 1.0)  # x < 0: the left half of the image
    cam = ortho_camera(w, h)
    if kind == "PERSP":  # from z = 5, 11.5 units wide at the card, its edge in the centre
        cam = Camera(matrix_world=cam.matrix_world, width=w, height=h, type="PERSP",
                     lens=12.5, sensor_width=36.0, sensor_fit="HORIZONTAL")
    film = {"spp": 64, "distance": 0.5, "filter_width": 1.5}
    plain = render_film(floor, cam, **film)
    held = render_film(floor, cam, holdout=card, **film)
    assert plain.holdout is None and held.holdout is not None
    np.testing.assert_allclose(held.alpha + held.holdout, 1.0, atol=1e-6)
    assert np.all(held.ao[held.holdout == 1.0] == 1.0)
    left, right = held.holdout[:, :6], held.holdout[:, 10:]
    assert np.all(left == 1.0) and np.all(held.alpha[:, :6] == 0.0)
    assert np.all(right == 0.0)
    assert np.array_equal(held.ao[:, 10:], plain.ao[:, 10:])
    assert np.array_equal(held.alpha[:, 10:], plain.alpha[:, 10:])
    edge = held.holdout[:, 7:9]
    assert np.all((edge > 0.0) & (edge < 1.0))  # the filter blends the card's edge
    centres = render_film(floor, cam, holdout=card, **{**film, "filter_width": 0.0})
    assert np.array_equal(centres.holdout, (centres.holdout > 0).astype(np.float32))
    assert np.all(centres.holdout[:, :8] == 1.0) and np.all(centres.holdout[:, 8:] == 0.0)
    with pytest.raises(ValueError, match="holdout"):
        render_film(floor, cam, holdout=half_plane(0.0), **film)
    with pytest.raises(ValueError, match="holdout .*two-level"):
        render_film(half_plane(100.0), cam, holdout=half_plane(0.0), **film)
