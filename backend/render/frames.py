"""The frame renderer that `scenesort render-frames` (and each Ray worker) runs: a bundle's
frames in any order, each the service's camera job on the frame's instance list, with the
BVHs kept between frames (render/bvhs.py's skip rules); the frames' files and progress.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scenesort.backend.render.bundle import Bundle, read_bundle
from scenesort.backend.render.bvhs import BuildReport
from scenesort.backend.render.camera_render import job_camera, job_png, render_camera
from scenesort.backend.wire import binary as wire
from scenesort.backend.work.jobs import Job
from scenesort.backend.work.store import Store

DEFAULT_CACHE_BYTES = 4096 * 2**20


@dataclass
class FrameResult:
    """One rendered frame: AO, coverage and depth (height, width) float32, row 0 at the
    top, as the service's job result has them; its PNG; what the build did; timings."""

    frame: int
    ao: np.ndarray
    coverage: np.ndarray
    depth: np.ndarray
    png: bytes
    build: BuildReport
    timings_ms: dict[str, float]


class FrameRenderer:
    """Renders a bundle's frames in any order, keeping the BVHs between them (`cache_bytes`
    bounds what it keeps). Each frame is the service's camera job on the frame's instance
    list, so the images are the service's; `cull` False builds what is out of view too
    (the same images: the tests' and benchmarks' reference)."""

    def __init__(self, bundle: Bundle | str | Path, *, device: str | None = None,
                 threads: int | None = None, cache_bytes: int = DEFAULT_CACHE_BYTES,
                 cull: bool = True) -> None:
        # Anything with the Bundle's frame() and mesh(): render/cluster.py ships frames in
        # tasks and meshes through Ray's object store.
        self.bundle = read_bundle(bundle) if isinstance(bundle, str | Path) else bundle
        self.device = device or "cpu"
        self.threads = threads
        self.store = Store(cache_bytes)
        self.cull = cull  # False: every mesh built, the top level over every instance

    def _mesh(self, mesh_id: str) -> wire.SceneArrays:
        found = self.store.get(mesh_id)
        if found is None:
            found = self.bundle.mesh(mesh_id)
            self.store.put(mesh_id, found, found.nbytes)
        return found

    def render(self, frame_number: int) -> FrameResult:
        """Render one frame (its meshes read from the bundle when first needed)."""
        frame = self.bundle.frame(frame_number)
        request = frame.request
        scene = wire.resolve(frame.instances, self._mesh)
        camera = job_camera(request)
        job = Job(job_id=f"frame-{frame_number}", scene_id=scene.scene_id,
                  width=camera.width, height=camera.height)
        options = frame.options.with_(threads=self.threads)
        render_camera(job, self.store, scene, camera, options, request.method,
                      request.leaf_size, self.device, cull=self.cull)
        assert job.ao is not None and job.coverage is not None and job.depth is not None
        return FrameResult(frame_number, job.ao, job.coverage, job.depth, job_png(job) or b"",
                           job.build or BuildReport(), dict(job.timings_ms))


def frame_paths(out_dir: Path, frame_number: int) -> tuple[Path, Path]:
    """Where a frame's 8-bit PNG and float32 AO (.npy) go."""
    stem = Path(out_dir) / f"{frame_number:06d}"
    return stem.with_suffix(".png"), stem.with_suffix(".npy")


def frame_done(out_dir: Path, frame_number: int) -> bool:
    """Whether the frame's files are in `out_dir` (what `resume` skips)."""
    return all(path.exists() for path in frame_paths(out_dir, frame_number))


def write_frame(out_dir: str | Path, frame_number: int, result: FrameResult) -> Path:
    """Write the frame's PNG (the service's `format=png`) and its float32 AO as .npy
    (row 0 at the top); returns the PNG's path."""
    png, npy = frame_paths(Path(out_dir), frame_number)
    png.parent.mkdir(parents=True, exist_ok=True)
    np.save(npy, result.ao.astype(np.float32))
    png.write_bytes(result.png)  # last: a frame counts as done (resume) once its PNG exists
    return png


@contextmanager
def frame_progress(total: int, enabled: bool = True) -> Iterator[Callable[[int], None]]:
    """A rich progress bar over `total` frames; yields `advance(frame)`, called as each frame
    is done (a no-op when not `enabled`)."""
    if not enabled:
        yield lambda number: None
        return
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
               TimeElapsedColumn(), TimeRemainingColumn())
    with Progress(*columns, transient=True) as bar:
        task = bar.add_task("frames", total=total)
        yield lambda number: bar.update(task, advance=1, description=f"frame {number}")


def render_frames(bundle_path: str | Path, out_dir: str | Path, *,
                  frames: Iterable[int] | None = None, resume: bool = False,
                  threads: int | None = None, progress: bool = True,
                  device: str | None = None) -> list[tuple[int, BuildReport | None]]:
    """Render the bundle's frames (all, or `frames`) into `out_dir`, with a rich progress
    bar; `resume` skips frames whose files exist. Returns (frame, report) per frame, the
    report None for a frame skipped."""
    renderer = FrameRenderer(bundle_path, device=device, threads=threads)
    wanted = list(renderer.bundle.frames if frames is None else frames)
    done: list[tuple[int, BuildReport | None]] = []
    with frame_progress(len(wanted), progress) as advance:
        for number in wanted:
            if resume and frame_done(Path(out_dir), number):
                done.append((number, None))
            else:
                result = renderer.render(number)
                write_frame(out_dir, number, result)
                done.append((number, result.build))
            advance(number)
    return done
