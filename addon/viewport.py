"""The Rendered viewport: the 3D view's AO, refined progressively off Blender's main thread.

The engine's `view_update` and `view_draw` are thin (engine.py); the work is a
`ViewSession`'s, which headless tests drive with real depsgraphs:

- the scene goes as an instance list (`export.export_instances`), on the same service
  caches as F12: a mesh is sent only when the service lacks it (so moving an object sends
  the list alone and builds the top level, an edit re-sends and refits that mesh, and an
  F12 afterwards sends and builds nothing); it is exported again only after an update
  that can change AO (geometry or transforms, not materials or lights); while it is the
  same scene, a restart sends its first job at once, on the connection kept from the
  last (a 404 sends it again);
- the view is the region's own projection (`region_camera`): perspective, orthographic
  and the camera view with its zoom and offset, at the region's size over Blender's
  viewport Pixel Size;
- rounds of service jobs: a first image at 4x the pixel size and 1 sample per pixel,
  then at full size 1 sample per pixel, then doubling, each round with seeds of its own,
  averaged into the image until the Viewport Samples are reached; or, with a Viewport
  Target Error T, after the 1-sample round the final render's adaptive jobs to 4T, 2T and
  T, each image replacing the last (about 1.3x the work of one job to T, where doubling
  uniform rounds takes several times it); pixel centres (the film's filter, which F12
  applies, would double a round's cost); no Z pass is traced;
  a new view or scene cancels the job in flight (`Task.cancel`: the service's job is
  cancelled too) and starts again.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from . import export, pipeline
from .ao_options import MIN_ADAPTIVE_SPP
from .client import ServiceError
from .connection import Connection, Target
from .image import film_alpha
from .tasks import Cancelled, Task

ROUND_SEED = 7919  # round k's seed is the render seed + k * ROUND_SEED: independent samples
MAX_TARGET = 0.99  # target_error stays below 1 (AoOptions)


def region_camera(view_matrix: Any, window_matrix: Any, width: int, height: int) -> dict:
    """The service's camera (`kernels.Camera.to_dict()` form) of a 3D view: its
    world-to-view matrix and OpenGL projection (`RegionView3D.view_matrix`,
    `window_matrix`, or a camera's `calc_matrix_camera`) at `width` x `height` pixels.
    The projection's frustum becomes the sensor (fitted across the width) and shift; its
    near and far planes the clip range. ValueError for a degenerate view."""
    if width < 1 or height < 1:
        raise ValueError(f"The view is {width}x{height} pixels: nothing to render")
    p = np.asarray(window_matrix, np.float64)
    view = np.asarray(view_matrix, np.float64)
    if p.shape != (4, 4) or view.shape != (4, 4) or not (np.isfinite(p).all()
                                                         and np.isfinite(view).all()):
        raise ValueError("The view's matrices must be finite 4x4 matrices")
    if p[0, 0] <= 0.0 or p[1, 1] <= 0.0:
        raise ValueError("The view's projection is degenerate (zero or negative scale)")
    to_world = np.linalg.inv(view)
    perspective = p[3, 3] == 0.0
    if perspective:
        s = 2.0 / p[0, 0]  # the frustum's width at depth 1
        shift = (p[0, 2] / 2.0, p[1, 2] / p[1, 1] * p[0, 0] / 2.0)
        near, far = p[2, 3] / (p[2, 2] - 1.0), p[2, 3] / (p[2, 2] + 1.0)
        lens = {"type": "PERSP", "lens": 36.0 / s}
    else:
        s = 2.0 / p[0, 0]  # the view's width
        shift = (-p[0, 3] / 2.0, -p[1, 3] / p[1, 1] * p[0, 0] / 2.0)
        near, far = (p[2, 3] + 1.0) / p[2, 2], (p[2, 3] - 1.0) / p[2, 2]
        # Orthographic rays start on the camera's plane: put it at the near plane (a view
        # behind the scene's front has near < 0).
        to_world[:3, 3] += to_world[:3, :3] @ np.array([0.0, 0.0, -near])
        near, far = 0.0, far - near
        lens = {"type": "ORTHO", "ortho_scale": s}
    return {
        "matrix_world": to_world.tolist(), "width": int(width), "height": int(height),
        **lens, "sensor_width": 36.0, "sensor_fit": "HORIZONTAL",
        "shift_x": float(shift[0]), "shift_y": float(shift[1]),
        "clip_start": float(max(near, 0.0)), "clip_end": float(far),
    }


def region_view(view_matrix: Any, window_matrix: Any, width: int, height: int,
                pixel_size: int) -> dict:
    """A job's view (`camera.view()` form) of the region at `pixel_size` screen pixels
    per rendered pixel."""
    size = (max(1, width // pixel_size), max(1, height // pixel_size))
    return {"camera": region_camera(view_matrix, window_matrix, *size), "window": None,
            "pixel_aspect": [1.0, 1.0]}


PREVIEW_SCALE = 4  # the first look's pixel size over the view's: 1/16 of the rays (Cycles
# starts coarser still, near 64 pixels across)


def coarser(view: dict) -> dict | None:
    """`view` at PREVIEW_SCALE times the pixel size (the same frustum), or None when that
    is too small to show anything (under 8 pixels across)."""
    cam = view["camera"]
    if min(cam["width"], cam["height"]) < 8 * PREVIEW_SCALE:
        return None
    return {**view, "camera": {**cam, "width": cam["width"] // PREVIEW_SCALE,
                               "height": cam["height"] // PREVIEW_SCALE}}


def pixel_size(scene: Any, preferences_scale: float = 1.0) -> int:
    """Blender's viewport Pixel Size (Render Properties > Performance > Viewport): AUTO
    follows the interface's resolution scale, as Cycles' does."""
    value = scene.render.preview_pixel_size
    return max(1, round(preferences_scale)) if value == "AUTO" else int(value)


def schedule(total: int) -> list[int]:
    """Samples per round: 1, then doubling, summing to `total`."""
    rounds, done, step = [], 0, 1
    while done < total:
        n = min(step, total - done)
        rounds.append(n)
        done += n
        step = max(1, done)
    return rounds


# AO changes only with geometry and placement: other updates (materials, lights, the world's
# colour) render nothing new. The World's AO distance is in the settings, compared apart.
def changes(updates: Any) -> tuple[bool, bool]:
    """Whether depsgraph updates can change the AO image's scene, and whether some mesh
    data may have changed (else only placements did: the meshes read before still hold)."""
    moved = geometry = False
    for u in updates:
        geometry |= u.is_updated_geometry
        moved |= u.is_updated_transform
    return moved or geometry, geometry


def binomial_rmse(mean: np.ndarray, coverage: np.ndarray, samples: int) -> float | None:
    """The viewport's error estimate: the RMSE over covered pixels of a mean of `samples`
    independent 0/1 AO samples per pixel, whose variance is m (1 - m) / (n - 1) with the
    unbiased sample variance (None below 2 samples, where it is unknown, and with nothing
    covered). An upper estimate: each round's Sobol points are stratified, so the true
    error is lower. (A round's own `rmse_estimate` cannot be combined: at 1 sample per
    pixel it knows no variance either.)"""
    m = mean[coverage > 0]
    if not len(m) or samples < 2:
        return None
    return float(np.sqrt(np.mean(m * (1.0 - m)) / (samples - 1)))


@dataclass(frozen=True)
class Frame:
    """What the viewport shows: RGBA (height, width, 4) float32 bottom row first (the
    texture's order), the samples so far and the estimated RMSE (None: unknown)."""

    rgba: np.ndarray
    spp: int
    rmse: float | None
    done: bool
    at: float  # time.perf_counter() when it was made


class ViewSession:
    """The Rendered viewport's work for one 3D view (see the module docstring). Main
    thread: `update_scene`, `look`, `frame`, `stop`; the rounds run on a worker thread."""

    def __init__(self, target: Target) -> None:
        self.target = target
        self.scene: export.InstanceExport | None = None
        self.settings: pipeline.Settings | None = None
        self.view: dict | None = None
        self.transparent = False
        self.exports = 0  # how often the scene was read from Blender
        self.meshes = export.MeshCache()  # its meshes, while no geometry changes
        # every round's, oldest first (their images let go once shown)
        self.outcomes: list[pipeline.Outcome] = []
        self.checks: list[pipeline.Outcome] = []  # what each check of a new scene sent
        self.started = 0.0  # time.perf_counter() of the last start over
        self.error: str | None = None
        self._frame: Frame | None = None
        self._task: Task | None = None
        self._lock = threading.Lock()
        # worker threads': the connection and the id of the scene last checked on it
        self._checked: tuple[Connection, str] | None = None

    # --- main thread ------------------------------------------------------------------

    def update_scene(self, depsgraph: Any, first: bool = False) -> None:
        """`view_update`: read the scene again if an update can change AO (or `first`),
        take the settings, and start over if either changed."""
        scene = depsgraph.scene
        settings = replace(pipeline.Settings.from_scene(scene), engine="bvh",
                           spp=int(scene.scenesort.viewport_spp),
                           target_error=float(scene.scenesort.viewport_target_error),
                           max_pixel_error=0.0, denoise=False,
                           filter_width=0.0)  # pixel centres: a filter's camera rays
        # would double a round's cost (F12 renders through the film's filter)
        self.transparent = bool(scene.render.film_transparent)
        changed = settings != self.settings
        scene_changed, geometry = changes(depsgraph.updates)
        if first or geometry:
            self.meshes.clear()
        if first or self.scene is None or scene_changed:
            listing = export.export_instances(depsgraph, self.meshes)
            self.exports += 1
            changed |= self.scene is None or listing.scene_id != self.scene.scene_id
            self.scene = listing
        self.settings = settings
        if changed:
            self._restart()

    def look(self, view: dict) -> None:
        """`view_draw`: the region's view; a new one starts over."""
        if view != self.view:
            self.view = view
            self._restart()

    def frame(self) -> Frame | None:
        with self._lock:
            return self._frame

    @property
    def refining(self) -> bool:
        return self._task is not None and not self._task.done

    def stop(self) -> None:
        """Cancel the job in flight (its service job too)."""
        if self._task is not None:
            self._task.cancel()

    def wait(self, timeout: float | None = None) -> None:
        """Block until the rounds in flight end (tests, benchmarks)."""
        if self._task is not None:
            self._task.join(timeout)

    # --- worker thread ----------------------------------------------------------------

    def _restart(self) -> None:
        self.stop()
        if self.scene is None or self.view is None or self.settings is None:
            return
        if self.scene.triangles == 0:
            self.error = "Nothing to render: no object with mesh triangles"
            return
        scene, view, settings = self.scene, self.view, self.settings
        self.started = time.perf_counter()
        self._task = Task(lambda task: self._rounds(task, scene, view, settings))
        self._task.start()

    def _rounds(self, task: Task, scene: export.InstanceExport, view: dict,
                settings: pipeline.Settings) -> None:
        try:
            try:
                self._run(task, scene, view, settings, self._ready(task, scene, settings))
            except ServiceError as exc:
                if exc.status != 404:
                    raise
                self._checked = None  # the service forgot the scene (or restarted): again
                self._run(task, scene, view, settings, self._ready(task, scene, settings))
            self.error = None
        except Cancelled:
            pass
        except Exception as exc:  # noqa: BLE001 - shown in the viewport's text
            self._checked = None
            self.error = str(exc)

    def _ready(self, task: Task, scene: export.InstanceExport,
               settings: pipeline.Settings) -> tuple[Connection, str]:
        """The connection and the scene's id on it: as last time while the scene is the
        same (a view change makes no request before its job), else `pipeline.prepare`'s."""
        checked = self._checked
        if checked is None or checked[1] != scene.scene_id:
            client, outcome, scene_id = pipeline.prepare(task, self.target, settings, scene)
            outcome.requests = list(client.requests)
            self.checks.append(outcome)
            assert outcome.connection is not None
            checked = self._checked = (outcome.connection, scene_id)
        return checked

    def _run(self, task: Task, scene: export.InstanceExport, view: dict,
             settings: pipeline.Settings, ready: tuple[Connection, str]) -> None:
        connection, scene_id = ready

        def job(spp: int, seed: int, of: dict, target: float = 0.0) -> pipeline.Outcome:
            got = pipeline.camera_job(
                task, connection.client, pipeline.Outcome(connection=connection), scene_id,
                replace(settings, spp=spp, seed=seed, target_error=target), of,
                holdouts=scene.holdouts, depth=False)
            self.outcomes.append(got)
            return got

        coarse = coarser(view)
        if coarse is not None:  # a first look at a sixteenth of the rays
            got = job(1, settings.seed, coarse)
            self._publish(got, got.ao, 1, None, False)
        if settings.target_error > 0.0:
            got = job(1, settings.seed, view)
            self._publish(got, got.ao, 1, None, False)
            for k, scale in enumerate((4.0, 2.0, 1.0)):  # each independent, replacing
                target = min(scale * settings.target_error, MAX_TARGET)
                got = job(MIN_ADAPTIVE_SPP, settings.seed + (k + 1) * ROUND_SEED, view, target)
                self._publish(got, got.ao, round(got.spp_mean), got.rmse_estimate,
                              scale == 1.0)
            return
        total, mean = 0, None
        rounds = schedule(settings.spp)
        for k, n in enumerate(rounds):
            got = job(n, settings.seed + k * ROUND_SEED, view)
            w = n / (total + n)
            mean = got.ao if mean is None else (1.0 - w) * mean + w * got.ao
            total += n
            self._publish(got, mean, total, binomial_rmse(mean, got.coverage, total),
                          k == len(rounds) - 1)

    def _publish(self, got: pipeline.Outcome, mean: np.ndarray, spp: int,
                 rmse: float | None, done: bool) -> None:
        width, height = got.size
        coverage = got.coverage.reshape(height, width)
        alpha = film_alpha(coverage, None if got.holdout is None
                           else got.holdout.reshape(height, width), self.transparent)
        grey = mean.reshape(height, width) * coverage
        rgba = np.stack([grey, grey, grey, alpha], axis=-1)[::-1]
        with self._lock:
            self._frame = Frame(np.ascontiguousarray(rgba, np.float32), spp, rmse, done,
                                time.perf_counter())
        got.ao = got.coverage = got.holdout = None  # a long session keeps no old images


def draw_frame(frame: Frame, width: int, height: int) -> None:
    """Draw `frame` over the region (`width` x `height`), stretched when the Pixel Size
    made it smaller; inside the engine's display space shader, so the scene's colour
    management applies. Needs a GPU context: never called headless."""
    import gpu
    from gpu_extras.presets import draw_texture_2d

    h, w = frame.rgba.shape[:2]
    buffer = gpu.types.Buffer("FLOAT", w * h * 4, frame.rgba.ravel())
    texture = gpu.types.GPUTexture((w, h), format="RGBA16F", data=buffer)
    gpu.state.blend_set("ALPHA_PREMULT")
    draw_texture_2d(texture, (0, 0), width, height)
    gpu.state.blend_set("NONE")


def status_text(session: ViewSession) -> str:
    """The viewport's statistics line: samples and estimated error, or what went wrong."""
    if session.error:
        return f"scenesort: {session.error}"
    frame = session.frame()
    if frame is None:
        return "scenesort: starting"
    rmse = "-" if frame.rmse is None else f"{frame.rmse:.4f}"
    state = "done" if frame.done else "refining"
    settings = session.settings
    if settings is not None and settings.target_error > 0.0:
        return (f"Sample {frame.spp} (mean) | est. RMSE {rmse}, target "
                f"{settings.target_error:.4f} | {state}")
    return f"Sample {frame.spp}/{settings.spp if settings else '?'} | est. RMSE {rmse} | {state}"
