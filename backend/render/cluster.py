"""A frame bundle rendered on a Ray cluster: `scenesort render-frames BUNDLE --ray ADDRESS`.

The driver reads the bundle, puts each mesh into Ray's object store once (a node fetches an
object once and every worker on it reads the same shared memory) and submits one task per
frame carrying only that frame's view and instance list. Each worker process keeps one
`FrameRenderer` per run, so the BVHs it built stay between the frames it renders (the skip
rules of render/bvhs.py, per worker). Images come back to the driver, which writes them
in frame order. A frame whose worker dies or raises is retried by Ray (`max_retries`); one
that keeps failing is reported by number and the others are still written. docs/cluster.md
has the set-up, what moves per frame and the cost model.
"""

from __future__ import annotations

import pickle
import time
import uuid
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from scenesort.backend.render.bundle import Frame, read_bundle
from scenesort.backend.render.bvhs import BuildReport
from scenesort.backend.render.frames import FrameRenderer, FrameResult, frame_done, write_frame

EXTRA_HINT = 'pip install "scenesort[cluster]"'
DEFAULT_RETRIES = 3
# Frames in flight (or done, waiting for an earlier one to be written) per engine slot of the
# cluster: enough to keep every worker busy while the driver writes, few enough that deformed
# meshes and images do not pile up in the object store or the driver.
IN_FLIGHT_PER_SLOT = 2


class ClusterError(RuntimeError):
    """Ray missing or unreachable; the message says what to install or check."""


def import_ray() -> Any:
    try:
        import ray
    except ImportError:
        raise ClusterError(f"--ray needs Ray, an optional extra: {EXTRA_HINT}") from None
    return ray


def connect(ray: Any, address: str | None, workers: int | None) -> float:
    """Join (or start) the cluster; the seconds it took. `address`: "local" starts a new
    cluster on this machine with `workers` CPUs; None is Ray's default (RAY_ADDRESS, else a
    new local one); anything else ("auto", "HOST:PORT", "ray://HOST:10001") is an existing
    cluster. An already connected driver (a caller's own ray.init) is reused."""
    start = time.perf_counter()
    if ray.is_initialized():
        return 0.0
    options: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False,
                               "logging_level": "WARNING"}
    if address == "local":
        options["num_cpus"] = workers
    elif address is not None:
        options["address"] = address
    try:
        ray.init(**options)
    except (ConnectionError, ValueError, RuntimeError) as exc:
        raise ClusterError(f"--ray {address}: cannot reach the Ray cluster ({exc}); start one "
                           "with `ray start --head` or use --ray local") from None
    return time.perf_counter() - start


@dataclass
class ShippedBundle:
    """The bundle as a worker sees it: frames arrive with their tasks, meshes from the
    object store (what FrameRenderer reads of a Bundle)."""

    frames: dict[int, Frame] = field(default_factory=dict)
    meshes: dict[str, Any] = field(default_factory=dict)  # mesh id -> ObjectRef

    def frame(self, number: int) -> Frame:
        return self.frames[number]

    def mesh(self, mesh_id: str) -> Any:
        import ray

        return ray.get(self.meshes[mesh_id])  # zero-copy: numpy views of shared memory


# Per worker process: run id -> its renderer (kept between the tasks of one run).
_RENDERERS: dict[str, FrameRenderer] = {}


def render_task(run: str, frame: Frame, meshes: dict[str, Any], threads: int,
                device: str | None) -> FrameResult:
    """One frame on a worker (a Ray task: module level so that workers import it)."""
    renderer = _RENDERERS.get(run)
    if renderer is None:
        _RENDERERS.clear()  # a new run: the previous run's BVHs are not needed any more
        renderer = _RENDERERS[run] = FrameRenderer(ShippedBundle(), device=device,
                                                   threads=threads)
    shipped = renderer.bundle
    shipped.frames[frame.number] = frame
    shipped.meshes.update(meshes)
    return renderer.render(frame.number)


@dataclass
class ClusterRun:
    """What a cluster render did: frames written, skipped (resume), failed (number ->
    message), the cluster's start-up apart from the render, and bytes per frame."""

    written: list[int] = field(default_factory=list)
    skipped: list[int] = field(default_factory=list)
    failed: dict[int, str] = field(default_factory=dict)
    builds: dict[int, BuildReport] = field(default_factory=dict)  # what each frame built
    startup_s: float = 0.0
    render_s: float = 0.0
    sent_bytes: dict[int, int] = field(default_factory=dict)  # task arguments + new meshes
    returned_bytes: dict[int, int] = field(default_factory=dict)  # the frame's images
    submit_s: float = 0.0  # the driver's time reading, putting and submitting frames


def _failure(exc: BaseException) -> str:
    """A failed task's message: what it raised, else the last line of Ray's error."""
    text = str(exc).strip().splitlines()
    cause = getattr(exc, "cause", None)  # RayTaskError: the exception the task raised
    return str(cause) if cause is not None else (text[-1] if text else type(exc).__name__)


def render_frames_ray(bundle_path: str | Path, out_dir: str | Path, *,
                      address: str | None = None, frames: Iterable[int] | None = None,
                      resume: bool = False, threads: int = 1, workers: int | None = None,
                      retries: int = DEFAULT_RETRIES, gpus: float = 0.0,
                      on_frame: Callable[[int], None] | None = None) -> ClusterRun:
    """Render the bundle's frames (all, or `frames`) as Ray tasks into `out_dir`, written in
    frame order as `render_frames` writes them. `threads`: engine threads per task (its
    CPUs); `workers`: the CPUs of a cluster started with address="local"; `gpus`: GPUs per
    task (the task renders on CUDA when > 0). `on_frame(frame)` as each frame is done
    (skipped, written or failed)."""
    ray = import_ray()
    bundle = read_bundle(bundle_path)
    out = Path(out_dir)
    wanted = list(bundle.frames if frames is None else frames)
    run = ClusterRun()
    todo = []
    for number in wanted:
        (run.skipped if resume and frame_done(out, number) else todo).append(number)
    views = {number: bundle.frame(number) for number in todo}  # bad frames fail here, early
    report = on_frame or (lambda number: None)
    for number in run.skipped:
        report(number)
    run.startup_s = connect(ray, address, workers)
    start = time.perf_counter()
    task = ray.remote(render_task)
    options = {"num_cpus": threads, "num_gpus": gpus, "max_retries": retries,
               "retry_exceptions": True}
    device = "cuda" if gpus > 0 else None
    slots = max(1, int(ray.cluster_resources().get("CPU", 1) // threads))
    refs: dict[str, Any] = {}  # mesh id -> ObjectRef, put once per mesh while frames need it
    pending: dict[Any, int] = {}  # task ref -> frame
    using: dict[int, list[str]] = {}  # frame in flight -> the meshes it uses
    finished: dict[int, FrameResult | BaseException] = {}
    next_write = 0
    run_id = uuid.uuid4().hex

    def submit(number: int) -> None:
        began = time.perf_counter()
        frame = views.pop(number)
        ids = list(frame.instances.mesh_ids)
        for stale in set(refs) - set(ids) - {m for v in using.values() for m in v}:
            del refs[stale]  # no frame in flight needs it: Ray may free it
        new = {m: bundle.mesh(m) for m in ids if m not in refs}
        refs.update({m: ray.put(mesh) for m, mesh in new.items()})
        args = (run_id, frame, {m: refs[m] for m in ids}, threads, device)
        # What the driver sends for this frame: the task's arguments, the object ids of its
        # meshes (pickling the refs themselves would pin them) and the meshes first put for it.
        run.sent_bytes[number] = (len(pickle.dumps((run_id, frame, threads, device)))
                                  + sum(len(m) + len(refs[m].binary()) for m in ids)
                                  + sum(mesh.nbytes for mesh in new.values()))
        pending[task.options(name=f"frame {number}", **options).remote(*args)] = number
        using[number] = ids
        run.submit_s += time.perf_counter() - began

    queue = list(todo)
    while queue or pending:
        # results waiting for an earlier frame count too: what the driver holds stays bounded
        while queue and len(pending) + len(finished) < slots * IN_FLIGHT_PER_SLOT:
            submit(queue.pop(0))
        ready, _ = ray.wait(list(pending), num_returns=1)
        number = pending.pop(ready[0])
        using.pop(number)
        try:
            result = ray.get(ready[0])
            run.returned_bytes[number] = result.ao.nbytes * 3 + len(result.png)
            finished[number] = result
        except Exception as exc:  # Ray wraps what the task raised, or its worker's death
            finished[number] = exc
        while next_write < len(todo) and todo[next_write] in finished:
            done = todo[next_write]
            outcome = finished.pop(done)
            if isinstance(outcome, BaseException):
                run.failed[done] = _failure(outcome)
            else:
                write_frame(out, done, outcome)
                run.written.append(done)
                run.builds[done] = outcome.build
            next_write += 1
            report(done)
    run.render_s = time.perf_counter() - start
    return run
