"""The steps of Build BVH and of every render: upload only when needed, build, render.

Runs inside a `Task` (main thread or worker): inputs are plain snapshots taken from
Blender beforehand, outputs are plain dicts and arrays applied afterwards.
"""

from __future__ import annotations

import contextlib
import functools
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from .client import Client, ServiceError
from .connection import Connection, Target, connect
from .export import InstanceExport, SceneMesh
from .tasks import Cancelled, Task

NO_WORLD_AO_DISTANCE = 10.0  # Cycles' AO distance in a scene without a World
NOTHING_TO_SEND = ("The scene has no visible, renderable mesh triangles to send: "
                   "unhide an object or enable it for rendering")


def ao_distance(scene: Any) -> float:
    """The AO distance Cycles' AO pass uses: the World's (World > Ambient Occlusion >
    Distance), or the panel's `ao_distance` where that is set (> 0) to override it."""
    override = float(scene.scenesort.ao_distance)
    if override > 0.0:
        return override
    world = scene.world
    return float(world.light_settings.distance) if world is not None else NO_WORLD_AO_DISTANCE


def film_filter(scene: Any) -> tuple[str, float]:
    """The pixel filter Cycles renders `scene` with (Film > Pixel Filter): its type and
    width in pixels from `scene.cycles` where the Cycles add-on is enabled (Cycles renders
    Box 1 px wide whatever the width says: blender/sync.cpp), else Blackman-Harris (Cycles'
    default type) at `scene.render.filter_size`."""
    cycles = getattr(scene, "cycles", None)
    if cycles is not None and hasattr(cycles, "pixel_filter_type"):
        kind = str(cycles.pixel_filter_type)
        return kind, 1.0 if kind == "BOX" else float(cycles.filter_width)
    return "BLACKMAN_HARRIS", float(scene.render.filter_size)


@dataclass(frozen=True)
class Settings:
    """A snapshot of `scene.scenesort` (and the World's AO distance), safe to read off the
    main thread."""

    method: str
    leaf_size: int
    spp: int
    target_error: float
    max_pixel_error: float
    ao_distance: float  # what the render uses: `ao_distance(scene)`
    seed: int
    engine: str
    denoise: bool = False
    pixel_filter: str = "BLACKMAN_HARRIS"  # `film_filter(scene)`; width 0: pixel centres
    filter_width: float = 0.0

    @classmethod
    def from_scene(cls, scene: Any) -> Settings:
        props = scene.scenesort
        pixel_filter, filter_width = film_filter(scene)
        return cls(
            method=props.method,
            leaf_size=int(props.leaf_size),
            spp=int(props.spp),
            target_error=float(props.target_error),
            max_pixel_error=float(props.max_pixel_error),
            ao_distance=ao_distance(scene),
            seed=int(props.seed),
            engine=props.engine,
            denoise=bool(props.use_denoising),
            pixel_filter=pixel_filter,
            filter_width=filter_width,
        )


@dataclass
class Outcome:
    """What the service did: upload size, the build answer, the AO image."""

    connection: Connection | None = None  # the service that did it (health, started)
    scene_id: str = ""
    uploaded_bytes: int = 0
    build: dict | None = None
    job_id: str = ""
    size: tuple[int, int] = (0, 0)  # the image's width and height
    ao: np.ndarray | None = None  # height*width float32, row 0 at the top (1 on a miss)
    coverage: np.ndarray | None = None  # 1 where the camera ray hit, 0 where it missed
    depth: np.ndarray | None = None  # camera-space Z, 1e10 on a miss
    holdout: np.ndarray | None = None  # 1 where the camera sees a holdout (None: nowhere)
    # the job's extra passes by name (JobRequest.passes), each pixels * channels float32
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    timings_ms: dict[str, float] = field(default_factory=dict)  # the job's phases
    render_ms: float = 0.0
    # what the render achieved (the job's status): estimated RMSE (None: unknown), spp, rays
    rmse_estimate: float | None = None
    spp_mean: float = 0.0
    spp_max: int = 0
    rays: int = 0
    # what the job built, refit or reused (the job status's `build`; backend/render/bvhs.py)
    build_report: dict | None = None
    denoised: bool = False  # the image is OIDN's output (rmse_estimate is the raw render's)
    film: str = ""  # what the pixels are: the job status's `film` ("" for a bake)
    requests: list[str] = field(default_factory=list)

    @property
    def device(self) -> str:
        """The device that traced it, as the service's health answer names it ("cpu",
        "cuda:0")."""
        health = self.connection.health if self.connection is not None else {}
        return str(health.get("device", "unknown device"))


def remember(status: Any, outcome: Outcome) -> None:
    """What a render or bake achieved, for the panel's Last render box (the window
    manager's `scenesort` status; on the main thread)."""
    status.last_upload_bytes = outcome.uploaded_bytes
    status.last_render_ms = outcome.render_ms
    status.last_rmse = -1.0 if outcome.rmse_estimate is None else outcome.rmse_estimate
    status.last_spp_mean, status.last_spp_max = outcome.spp_mean, outcome.spp_max
    status.last_rays = outcome.rays
    status.last_device = outcome.device
    status.renders += 1


def check_size(outcome: Outcome, mesh: SceneMesh, what: str) -> None:
    """Refuse, before hashing or sending it, an upload larger than the service takes (its
    health answer's `max_body_bytes`, when it says)."""
    health = outcome.connection.health if outcome.connection is not None else {}
    limit = health.get("max_body_bytes")
    if limit is not None and mesh.nbytes > int(limit):
        raise ServiceError(
            f"{what} is {mesh.nbytes / 2**20:,.1f} MB to upload ({mesh.triangles:,} "
            f"triangles), more than the service takes ({int(limit) / 2**20:,.1f} MB, its "
            "--max-body-mb): start the service with a larger --max-body-mb, or render "
            "fewer or lighter objects (linked duplicates and collection instances send "
            "their mesh once)")


def ensure_scene(task: Task, client: Client, mesh: SceneMesh, outcome: Outcome) -> str:
    """The scene id on the service, uploading the scene only if the service lacks it."""
    if mesh.triangles == 0:
        raise ServiceError(NOTHING_TO_SEND)
    check_size(outcome, mesh, "The scene")
    task.set_step("hashing the scene")
    scene_id = mesh.content_id
    task.set_step("checking the service's scene cache")
    if not client.has_scene(scene_id):
        task.set_step(f"uploading {mesh.triangles:,} triangles ({mesh.nbytes / 1e6:.1f} MB)")
        # the blocks, not joined: a copy of the scene less in Blender's memory
        answer = client.upload_scene(len(mesh.vertices), mesh.triangles, mesh.blocks(),
                                     mesh.query(), stop=lambda: task.cancelled)
        outcome.uploaded_bytes = mesh.nbytes
        if answer.get("scene_id", scene_id) != scene_id:
            # Not fatal: use the service's id, but the next render will upload again.
            scene_id = answer["scene_id"]
    outcome.scene_id = scene_id
    return scene_id


def ensure_instances(task: Task, client: Client, scene: InstanceExport,
                     outcome: Outcome) -> str:
    """The instance list's id on the service, sending only what it lacks: each mesh after
    a HEAD by its hash, then the list itself (its own hash: an unchanged list, as when
    only the camera moved, is not sent again)."""
    if scene.triangles == 0:
        raise ServiceError(NOTHING_TO_SEND)
    task.set_step(f"checking {len(scene.meshes)} meshes on the service")
    for mesh in scene.meshes.values():
        check_size(outcome, mesh, "A mesh of the scene")
    for mesh_id, mesh in scene.meshes.items():
        if not client.has_mesh(mesh_id):
            task.set_step(f"uploading a mesh of {mesh.triangles:,} triangles "
                          f"({mesh.nbytes / 1e6:.1f} MB)")
            client.put_mesh(mesh_id, len(mesh.vertices), mesh.triangles, mesh.blocks(),
                            mesh.query(), stop=lambda: task.cancelled)
            outcome.uploaded_bytes += mesh.nbytes
    scene_id = scene.scene_id
    if not client.has_scene(scene_id):
        task.set_step(f"sending {scene.objects:,} instances")
        body = scene.body()
        client.upload_instances(len(scene.meshes), scene.objects, body,
                                scene.visibility is not None)
        outcome.uploaded_bytes += len(body)
    outcome.scene_id = scene_id
    return scene_id


def build(task: Task, target: Target, settings: Settings, mesh: SceneMesh) -> Outcome:
    """Make sure the scene is on the service and build (or reuse) its BVH."""
    client, outcome, _ = prepare(task, target, replace(settings, engine="bvh"), mesh)
    outcome.requests = client.requests
    return outcome


def prepare(
    task: Task, target: Target, settings: Settings, mesh: SceneMesh | InstanceExport
) -> tuple[Client, Outcome, str]:
    """What both renders do first: the service (started if allowed), the scene on it and,
    for the BVH engine and a flattened scene, its BVH (an instance list's job builds its
    own and says what it did). Returns the client, the outcome so far, the scene's id."""
    outcome = Outcome(connection=connect(task, target))
    client = outcome.connection.client
    if isinstance(mesh, InstanceExport):
        return client, outcome, ensure_instances(task, client, mesh, outcome)
    scene_id = ensure_scene(task, client, mesh, outcome)
    if settings.engine == "bvh":
        started = outcome.connection.started
        first = "; a new service compiles Warp's kernels first" if started else ""
        task.set_step(
            f"building the BVH ({settings.method}, leaf size {settings.leaf_size}{first})"
        )
        outcome.build = client.build_bvh(scene_id, settings.method, settings.leaf_size)
    return client, outcome, scene_id


# A poll waits on the service for the job's end (a long poll: a short job, as a viewport
# round, is seen as it ends) but no longer than this, so that progress shows this often.
# Esc does not wait for it: the task's cancel sends the job's at once (Task.cancelling).
# Each poll is a request the service's Python answers beside the job: polls every 30 ms
# slowed a 0.77 s film job by ~2.5% (notes, session 58).
JOB_POLL_S = 0.25


def _cancel_job(client: Client, job_id: str) -> None:
    """Cancel a job from the thread that cancels its task; one that already ended, or a
    service gone, answers with an error nobody waits for."""
    with contextlib.suppress(ServiceError):
        client.cancel_job(job_id)


def follow(task: Task, client: Client, job: dict, outcome: Outcome) -> dict:
    """Poll a service job until it ends, showing its progress; cancelling the task cancels
    the job. A job that did not finish is a ServiceError; a finished one's size, timings
    and statistics go into `outcome`, and its last status is returned."""
    outcome.job_id = job["job_id"]
    # a cancel reaches the job at once, not at the poll's end; set_step then raises Cancelled
    with task.cancelling(functools.partial(_cancel_job, client, job["job_id"])):
        while job["state"] in {"queued", "running"}:
            progress = float(job["progress"])
            task.set_step(f"{job['state']}: {job['phase'] or 'AO'} {100 * progress:.0f}%",
                          progress)
            job = client.job_status(job["job_id"], wait=JOB_POLL_S)
    if task.cancelled:  # the poll saw the job end as its cancel arrived
        raise Cancelled()
    if job["state"] != "done":
        raise ServiceError(
            f"The render job {job['state']}: {job.get('error') or 'no reason given'}"
        )
    outcome.size = (int(job["width"]), int(job["height"]))
    outcome.timings_ms = dict(job["timings_ms"])
    outcome.rmse_estimate = job.get("rmse_estimate")
    outcome.spp_mean = float(job.get("spp_mean") or 0.0)
    outcome.spp_max = int(job.get("spp_max") or 0)
    outcome.rays = int(job.get("rays") or 0)
    outcome.build_report = job.get("build")
    outcome.denoised = bool(job.get("denoised"))
    outcome.film = str(job.get("film") or "")
    return job


def job_fields(settings: Settings) -> dict[str, Any]:
    """The settings' fields of a service job (POST /v1/jobs), as a frame bundle keeps them."""
    fields: dict[str, Any] = {
        "spp": settings.spp,
        "seed": settings.seed,
        "engine": settings.engine,
        "method": settings.method,
        "leaf_size": settings.leaf_size,
        "distance": settings.ao_distance,
    }
    if settings.target_error:
        fields["target_error"] = settings.target_error
    if settings.max_pixel_error:
        fields["max_pixel_error"] = settings.max_pixel_error
    if settings.denoise:
        fields["denoise"] = True
    if settings.filter_width > 0.0:  # the service renders through it where it can
        fields["pixel_filter"] = settings.pixel_filter
        fields["filter_width"] = settings.filter_width
    return fields


def render_job(
    task: Task, target: Target, settings: Settings, mesh: SceneMesh | InstanceExport,
    view: dict, passes: tuple[str, ...] = (), depth: bool = True,
) -> Outcome:
    """The one render path (F12, animations, the panel's Render AO, scripts): scene, BVH,
    then a service job for `view` (`camera.view()`: camera, window, pixel aspect) with
    progress, keeping the extra `passes` (JobRequest.passes) and, with `depth`, the Z
    pass; cancelling the task cancels the job on the service."""
    client, outcome, scene_id = prepare(task, target, settings, mesh)
    holdouts = isinstance(mesh, InstanceExport) and mesh.holdouts
    return camera_job(task, client, outcome, scene_id, settings, view, passes, holdouts,
                      depth)


def camera_job(task: Task, client: Client, outcome: Outcome, scene_id: str,
               settings: Settings, view: dict, passes: tuple[str, ...] = (),
               holdouts: bool = False, depth: bool = True) -> Outcome:
    """`render_job`'s job, of a scene the service holds (`prepare`'s id): its images into
    `outcome` (the holdout layer with `holdouts`; no depth without `depth`)."""
    payload = {**view, "scene_id": scene_id, **job_fields(settings)}
    if not depth:
        payload["depth"] = False
    if passes:
        payload["passes"] = list(passes)
    start = time.perf_counter()
    task.set_step("queueing the render job")  # a task cancelled by now creates none
    job = follow(task, client, client.create_job(payload), outcome)
    pixels = outcome.size[0] * outcome.size[1]
    outcome.ao = client.job_result(job["job_id"], pixels)
    outcome.coverage = client.job_result(job["job_id"], pixels, "coverage")
    if depth:
        outcome.depth = client.job_result(job["job_id"], pixels, "depth")
    if holdouts:
        outcome.holdout = client.job_result(job["job_id"], pixels, "holdout")
    for name in passes:
        channels = {"object": 1, "triangle": 2}.get(name, 3)
        outcome.extras[name] = client.job_result(job["job_id"], pixels * channels, name)
    outcome.render_ms = (time.perf_counter() - start) * 1e3
    outcome.requests = client.requests
    return outcome


def bake_job(task: Task, target: Target, settings: Settings, mesh: SceneMesh,
             triangles: np.ndarray, u: np.ndarray, v: np.ndarray) -> Outcome:
    """A bake's path: the scene and its BVH as for a render, then a service surface job
    for the texels' points (scene triangle, u, v) with progress; cancelling the task
    cancels the job. `outcome.ao` holds one value per point."""
    settings = replace(settings, engine="bvh", denoise=False)  # what surface jobs trace
    client, outcome, scene_id = prepare(task, target, settings, mesh)
    fields = {name: value for name, value in job_fields(settings).items()
              if name not in ("engine", "denoise", "pixel_filter", "filter_width")}
    body = b"".join(np.ascontiguousarray(a, dtype).tobytes()
                    for a, dtype in ((triangles, "<i4"), (u, "<f4"), (v, "<f4")))
    start = time.perf_counter()
    task.set_step(f"sending {len(triangles):,} texels")
    job = follow(task, client, client.create_surface_job(scene_id, len(triangles), body, fields),
                 outcome)
    outcome.ao = client.job_result(job["job_id"], len(triangles))
    outcome.render_ms = (time.perf_counter() - start) * 1e3
    outcome.requests = client.requests
    return outcome
