"""Ambient occlusion per primary ray, with fixed or adaptive sample counts: `render_ao`,
`ambient_occlusion` and what they report (`AoResult`).

Definition (Cycles' AO pass): for a primary ray's closest hit p
with shading normal n, AO(p) = (1/pi) * integral over the hemisphere around n of
V(p, w) cos(theta) dw, where V = 1 when no triangle lies within `distance` along w. It is
estimated with cosine-weighted directions, so each sample is V itself (0 or 1) and the
estimate is the fraction of unoccluded occlusion rays. A primary ray that misses gets 1.0.
As in Cycles' `integrate_surface_ao`, every direction of the hemisphere about n is traced,
also those below the triangle's plane (dot(ng, w) <= 0, possible where n differs from
ng): they start on the viewer's side and count as occluded by whatever they meet, the
hit's own triangle included. (Cycles tested dot(Ng, D) > 0 and dropped such directions
until commit 48f7753, "Fix T95969, T91856: bake AO to vertex color artifacts after ray
offset removal", 2022, in Blender 3.1; 4.2 and 5.0 trace them.)

Guarantees:
- Occlusion rays never start inside the surface they leave (surface.py: the spawn point).
- `normals=None` is the geometric definition, bit for bit as before normals existed.
- Every sample is a pure function of (seed, ray index, sample index): the result is
  bit-identical for any thread count, round split or device.
- Skipped work: primary rays that miss the scene box are not traced, missed pixels get no
  occlusion rays, and (with an error target) converged pixels get no more samples.

The render by concept: scenesort/ao_options.py (AoOptions, every setting: beside the
engine, importable without Warp, for the service and the add-on too), primary.py (the primary
rays and their hits), surface.py (where and about which normal occlusion rays start),
tracers.py (what traces: a mesh's BVH, a scene, DACRT), adaptive.py (the rounds of
occlusion rays and when they stop: the error targets' rules and confidence).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import warp as wp

from scenesort.ao_options import DISTANCE_FRACTION, AoOptions

from ..bvh.api import Bvh
from ..core.launch import host_threads, load_modules
from ..core.record import Record, unset
from ..core.validate import as_rays, as_surface_points
from ..dacrt.api import dacrt_warp_modules
from ..scene.api import Placement, Scene, trace
from ..scene.top import WARP_MODULES as SCENE_MODULES
from . import primary, tracers
from .adaptive import Progress, SampleCounts, sample_rounds
from .denoise import denoise_ao, require_denoiser
from .primary import scene_shading, surface_hits, trace_primary
from .surface import PrimaryHits
from .tracers import check_tracer, occlusion_tracer


@dataclass(frozen=True, slots=True, kw_only=True)
class AoTimings(Record):
    """Where a render's time went, in ms."""

    compile: float  # Warp's (loading, on first use compiling, the kernels): not in total
    setup: float  # checks and the shading inputs
    primary: float
    occlusion: float
    denoise: float | None = unset()  # when denoised
    total: float


@dataclass(frozen=True, slots=True)
class AoRays(Record):
    """The rays a render traced."""

    primary: int  # those that entered the scene box
    occlusion: int
    rounds: int  # rounds of occlusion rays (a progress call before each)


@dataclass(frozen=True, slots=True)
class AoStats(Record):
    """What a render achieved."""

    rmse_estimate: float | None  # AoResult's
    spp_mean: float  # over hit pixels
    spp_max: int
    rays: int  # primary and occlusion
    denoised: bool


@dataclass
class AoResult:
    ao: np.ndarray  # (R,) float32 in [0, 1]
    spp_used: np.ndarray  # (R,) int32 occlusion samples per ray (0 where the ray missed)
    timings_ms: AoTimings
    rays: AoRays
    # Estimated RMSE over hit pixels against the converged AO (adaptive.py); None when no
    # ray hit. Always the raw render's, also when `denoised`.
    rmse_estimate: float | None
    # (R, 3) float32 unit shading normal of each primary hit (0 where the ray missed)
    normals: np.ndarray
    denoised: bool = False  # `ao` is OIDN's output (denoise=True)
    raw_ao: np.ndarray | None = None  # (R,) the render before denoising, when denoised
    holdout: np.ndarray | None = None  # (R,) bool: the ray's closest hit is a holdout's

    def stats(self) -> AoStats:
        """What the render achieved: estimated RMSE (of the raw render), mean and largest
        spp over hit pixels, rays traced (primary and occlusion), whether it was denoised."""
        hit = self.spp_used[self.spp_used > 0]
        return AoStats(rmse_estimate=self.rmse_estimate,
                       spp_mean=float(hit.mean()) if len(hit) else 0.0,
                       spp_max=int(hit.max()) if len(hit) else 0,
                       rays=self.rays.primary + self.rays.occlusion, denoised=self.denoised)


def default_distance(bvh: Bvh | Scene | Placement) -> float:
    """distance=None: DISTANCE_FRACTION of the scene box's diagonal (1.0 for an empty scene);
    of a Placement too, the same box before any BVH (backend/frames.py's culling)."""
    diag = float(np.linalg.norm(bvh.bounds[1].astype(np.float64) - bvh.bounds[0]))
    return DISTANCE_FRACTION * diag if math.isfinite(diag) and diag > 0.0 else 1.0


def render_ao(
    bvh: Bvh | Scene,
    origins: np.ndarray,
    directions: np.ndarray,
    options: AoOptions | None = None,
    *,
    tmin: float | np.ndarray = 0.0,
    tmax: float | np.ndarray = np.inf,
    normals: Any = None,
    terminator_offset: float | np.ndarray | None = None,
    image_shape: tuple[int, int] | None = None,
    progress: Progress | None = None,
    occluders: Bvh | Scene | None = None,
    holdout: Bvh | Scene | None = None,
    **settings: Any,
) -> AoResult:
    """AO per primary ray (see the module docstring for the definition and guarantees).

    `options`: an `AoOptions` (every setting, documented and checked there); keywords
    (`spp=64`, `target_error=0.02`, ...) set single fields of it; an unknown one raises
    TypeError naming it. Fixed mode (no error target): `spp` samples per hit pixel.
    Adaptive mode: samples are doubled in rounds up to `max_spp` per pixel until the
    targets are met (adaptive.py). `result.rmse_estimate` is the estimate in every mode.
    `normals`: None (geometric normals, flat shading) or (T, 3, 3) shading normals, one per
    corner of each of the BVH's triangles in index order (Blender's `Mesh.corner_normals`
    of the loop triangles; need not be unit; three zero corners mark a flat triangle).
    `terminator_offset`: Cycles' shadow terminator geometry offset, one number or (T,) per
    triangle in [0, 1] (None: the options'); only smooth triangles use it. Both arrays are
    read once per set of objects and taken as read-only.
    With a two-level `Scene` (kernels.scene.build_scene) instead of a Bvh: `normals` is None
    or one entry per mesh (None, or that mesh's (T_k, 3, 3) in object space; they are taken
    to world space by each instance's inverse transpose), `terminator_offset` one number or
    (I,) per instance, and engine="bvh" only; the rays and the AO are in world space.
    `progress(fraction, phase)` is called between rounds; an exception it raises cancels
    the render.
    `denoise=True` (needs the `scenesort[denoise]` extra, checked before tracing) runs
    OIDN on the image (`denoise.denoise_ao`): the rays must be a row-major `image_shape` =
    (height, width) image. `ao` is then the denoised image, `raw_ao` the render's own;
    `rmse_estimate` stays the raw render's (nothing measures the denoised error here).
    Ray visibility, as Cycles' AO pass has it: `bvh` is what the camera sees, `occluders`
    (None: `bvh`) what occlusion rays meet, so an object only in `bvh` is seen but casts no
    occlusion and one only in `occluders` occludes unseen. `holdout`: what the camera sees
    as holdout; a primary ray whose closest hit is there (no hit of `bvh` nearer) gets AO
    0 and no samples, and is marked in `result.holdout`. Shading normals and terminator
    offsets are `bvh`'s; all three must be on one device and, as Scenes, traced with
    engine="bvh".
    """
    opts = _options(options, settings)
    for traced in (bvh, occluders, holdout):
        if traced is not None:
            check_tracer(traced, opts.engine)
            if traced.device != bvh.device:
                raise ValueError("occluders and holdout must be on bvh's device")
    compile_ms = _load(bvh, opts)
    t_start = time.perf_counter()
    if opts.denoise:
        require_denoiser()
        if image_shape is None or int(np.prod(image_shape)) != len(origins):
            raise ValueError(f"denoise=True needs image_shape=(height, width) with height * "
                             f"width = the number of rays ({len(origins)}), got {image_shape!r}")
    origins, directions = as_rays(origins, directions)
    offsets = opts.terminator_offset if terminator_offset is None else terminator_offset
    scene_shading(bvh, normals, offsets)  # checked (and kept) before tracing
    report = _monotone(progress)
    setup_ms = (time.perf_counter() - t_start) * 1e3

    report(0.0, "primary")
    t0 = time.perf_counter()
    held = None
    if holdout is not None:  # the holdout's closest hit bounds the camera's (see above)
        first = trace(holdout, origins, directions, tmin, tmax, threads=opts.threads)
        held = first.hit
        tmax = np.where(held, first.t, np.asarray(tmax, np.float32))
    hits = trace_primary(bvh, origins, directions, tmin, tmax, opts.threads, opts.engine,
                         normals, offsets)
    if held is not None:
        held[hits.pixels] = False
    wp.synchronize_device(bvh.device)
    primary_ms = (time.perf_counter() - t0) * 1e3
    return _occlusion(bvh, hits, len(origins), opts, report, image_shape,
                      compile=compile_ms, setup=setup_ms, primary=primary_ms, start=t_start,
                      occluders=occluders, holdout=held)


def surface_ao(
    bvh: Bvh,
    triangles: np.ndarray,
    u: np.ndarray,
    v: np.ndarray,
    options: AoOptions | None = None,
    *,
    normals: Any = None,
    terminator_offset: float | np.ndarray | None = None,
    progress: Progress | None = None,
    **settings: Any,
) -> AoResult:
    """AO at given points of the mesh's own triangles, seen from the side each triangle's
    winding faces: a bake's texels. `triangles` (P,) index the BVH's triangles in the
    caller's order, `u` and `v` are the barycentric weights of their second and third
    corner. The definition, sampling, error target, shading arguments and guarantees are
    `render_ao`'s (engine "bvh", no denoising), with these points in place of the primary
    hits; a point on a triangle without area gets AO 1.0 and no samples, as a miss does."""
    opts = _options(options, settings)
    if opts.engine != "bvh" or opts.denoise:
        raise ValueError("surface_ao traces with engine='bvh' and does not denoise: drop "
                         "engine='dacrt' and denoise=True")
    check_tracer(bvh, opts.engine)
    if not isinstance(bvh, Bvh):
        raise TypeError(f"surface_ao takes a mesh's Bvh, got {type(bvh).__name__}")
    compile_ms = _load(bvh, opts)
    t_start = time.perf_counter()
    triangles, u, v = as_surface_points(triangles, u, v, len(bvh.indices))
    offsets = opts.terminator_offset if terminator_offset is None else terminator_offset
    report = _monotone(progress)
    setup_ms = (time.perf_counter() - t_start) * 1e3
    report(0.0, "surface")
    t0 = time.perf_counter()
    hits = surface_hits(bvh, triangles, u, v, normals, offsets)
    wp.synchronize_device(bvh.device)
    surface_ms = (time.perf_counter() - t0) * 1e3
    return _occlusion(bvh, hits, len(triangles), opts, report, None,
                      compile=compile_ms, setup=setup_ms, primary=surface_ms, start=t_start)


def _options(options: AoOptions | None, settings: dict[str, Any]) -> AoOptions:
    if options is not None and not isinstance(options, AoOptions):
        raise TypeError(f"options must be an AoOptions or None, got {options!r} (spp, "
                        f"distance and the other settings are keywords)")
    return (options or AoOptions()).with_(**settings)


def _load(bvh: Bvh | Scene, opts: AoOptions) -> float:
    """Load (on first use compile) the render's Warp modules: the ms it took, which is not
    rendering."""
    modules = (*primary.WARP_MODULES, *tracers.WARP_MODULES, *SCENE_MODULES,
               *(dacrt_warp_modules("pool") if opts.engine == "dacrt" else ()))
    return load_modules(bvh.device, *modules)


def _occlusion(bvh: Bvh | Scene, hits: PrimaryHits, r: int, opts: AoOptions,
               report: Progress, image_shape: tuple[int, int] | None, *, compile: float,
               setup: float, primary: float, start: float,
               occluders: Bvh | Scene | None = None,
               holdout: np.ndarray | None = None) -> AoResult:
    """The occlusion rounds from `hits` (of `r` primary rays or points) through `occluders`
    (None: `bvh`), the pixels (AO 0 where `holdout`), the denoiser if asked, and the result
    with its timings since `start`."""
    dist = default_distance(bvh) if opts.distance is None else opts.distance
    t0 = time.perf_counter()
    nthreads = host_threads(bvh.device, opts.threads)
    tracer = occlusion_tracer(bvh if occluders is None else occluders, hits, opts, dist,
                              nthreads)
    counts, rounds = sample_rounds(tracer, len(hits.pixels), opts, report)
    occlusion_ms = (time.perf_counter() - t0) * 1e3

    ao, spp_used, shading_normals = _pixels(r, hits, counts)
    if holdout is not None:
        ao[holdout] = 0.0
    raw_ao = denoise_ms = None
    if opts.denoise:
        t0 = time.perf_counter()
        raw_ao, ao = ao, denoise_ao(ao, shading_normals, spp_used > 0, image_shape)
        denoise_ms = (time.perf_counter() - t0) * 1e3
    timings = AoTimings(compile=compile, setup=setup, primary=primary,
                        occlusion=occlusion_ms, denoise=denoise_ms,
                        total=(time.perf_counter() - start) * 1e3)
    report(1.0, "done")
    return AoResult(ao=ao, spp_used=spp_used, timings_ms=timings,
                    rays=AoRays(primary=hits.traced, occlusion=int(counts.done.sum()),
                                rounds=rounds),
                    rmse_estimate=math.sqrt(counts.mse()) if len(hits.pixels) else None,
                    normals=shading_normals, denoised=opts.denoise, raw_ao=raw_ao,
                    holdout=holdout)


def _monotone(progress: Progress | None) -> Progress:
    """`progress` never called with a smaller fraction than before (adaptive estimates may
    dip; the bar never does)."""
    last = [0.0]

    def report(fraction: float, phase: str) -> None:
        last[0] = max(last[0], fraction)
        if progress is not None:
            progress(last[0], phase)

    return report


def _pixels(r: int, hits: PrimaryHits, counts: SampleCounts) -> tuple[np.ndarray, ...]:
    """Per primary ray (r of them): its AO, its samples and its hit's shading normal."""
    ao = np.ones(r, dtype=np.float32)
    spp_used = np.zeros(r, dtype=np.int32)
    normals = np.zeros((r, 3), dtype=np.float32)
    if len(hits.pixels):
        ao[hits.pixels] = (counts.open / counts.done).astype(np.float32)
        spp_used[hits.pixels] = counts.done.astype(np.int32)
        normals[hits.pixels] = hits.surfaces.numpy()["n"]
    return ao, spp_used, normals


def ambient_occlusion(bvh: Bvh | Scene, origins: np.ndarray, directions: np.ndarray,
                      options: AoOptions | None = None, **kwargs: Any) -> np.ndarray:
    """AO per primary ray, (R,) float32: `render_ao(...).ao` (the same arguments)."""
    return render_ao(bvh, origins, directions, options, **kwargs).ao
