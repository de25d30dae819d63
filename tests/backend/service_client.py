"""A real `scenesort serve` process on 127.0.0.1 with an ephemeral port, and a thin client.

`launch(args, log_path, env)` starts `python -m scenesort.backend.commands serve --port 0 ...`
with a fresh token in $SCENESORT_TOKEN (the way the add-on starts it), reads the port it bound
from its first stdout line and waits for /v1/health (bounded); `stop` ends it. Helpers live
here, not in conftest.py, so that test modules import them by a name no other test folder uses;
the fixtures `start_service`, `service` and `api` too (tests/backend/conftest.py and
tests/stability/conftest.py take them from here).
"""

from __future__ import annotations

import os
import queue
import secrets
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import pytest

from tests.waiting import WAIT_S, until

REPO = Path(__file__).resolve().parents[2]
START_TIMEOUT_S = 90.0  # first start may compile Warp kernels
READY_LINE = "scenesort serving on "


@dataclass
class Service:
    url: str
    proc: subprocess.Popen
    log_path: Path
    token: str | None = None
    first_line: str = ""

    @property
    def auth(self) -> dict[str, str]:
        """The Authorization header this service wants."""
        return {"Authorization": f"Bearer {self.token}"} if self.token else {}

    def log(self) -> str:
        """Everything the service wrote to stderr so far (its request log)."""
        return self.log_path.read_text(errors="replace")


def launch(
    args: tuple[str, ...], log_path: Path, env: dict[str, str | None] | None,
    preexec_fn: Callable[[], None] | None = None,
) -> Service:
    env = {"SCENESORT_TOKEN": secrets.token_urlsafe(24), **(env or {})}
    if "--no-token" in args:
        env.pop("SCENESORT_TOKEN")
    log_file = log_path.open("wb")
    proc = subprocess.Popen(
        [sys.executable, "-m", "scenesort.backend.commands", "serve", "--port", "0", *args],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=log_file,
        text=True,
        env={k: v for k, v in {**os.environ, **env}.items() if v is not None},
        preexec_fn=preexec_fn,
    )
    log_file.close()
    lines: queue.Queue[str] = queue.Queue()

    def pump() -> None:  # stdout must keep draining or the service could block on it
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.put(line)

    threading.Thread(target=pump, daemon=True).start()
    deadline = time.monotonic() + START_TIMEOUT_S
    url, first = None, ""
    while url is None and time.monotonic() < deadline and proc.poll() is None:
        try:
            line = lines.get(timeout=0.5)
        except queue.Empty:
            continue
        if line.startswith(READY_LINE):
            url, first = line[len(READY_LINE) :].split()[0], line
    service = Service(url or "", proc, log_path, env.get("SCENESORT_TOKEN"), first)
    if url is None:
        stop(service)
        raise RuntimeError(f"service did not start:\n{service.log()[-3000:]}")
    try:
        until(lambda: healthy(url), "/v1/health to answer 200", 20.0)
    except AssertionError:
        stop(service)
        raise RuntimeError(f"/v1/health never answered 200:\n{service.log()[-3000:]}") from None
    return service


def healthy(url: str) -> bool:
    try:
        return httpx.get(f"{url}/v1/health", timeout=2.0).status_code == 200
    except httpx.TransportError:
        return False


def stop(service: Service) -> None:
    if service.proc.poll() is None:
        service.proc.terminate()
        try:
            service.proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            service.proc.kill()
            service.proc.wait(timeout=15)


# --- scenes and a thin client -------------------------------------------------------


def floor_and_box(n: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """A 2x2 floor of n*n quads at y=0 under a closed unit box: AO between 0 and 1."""
    xs = np.linspace(-1.0, 1.0, n + 1, dtype=np.float32)
    gx, gz = np.meshgrid(xs, xs, indexing="ij")
    floor_v = np.stack([gx.ravel(), np.zeros(gx.size, np.float32), gz.ravel()], axis=1)
    quads = []
    for i in range(n):
        for j in range(n):
            a, b = i * (n + 1) + j, (i + 1) * (n + 1) + j
            quads += [[a, b, a + 1], [b, b + 1, a + 1]]
    corners = np.array(
        [[x, y, z] for x in (-0.3, 0.3) for y in (0.05, 0.65) for z in (-0.3, 0.3)], np.float32
    )
    faces = [
        [0, 1, 3],
        [0, 3, 2],
        [4, 6, 7],
        [4, 7, 5],
        [0, 4, 5],
        [0, 5, 1],
        [2, 3, 7],
        [2, 7, 6],
        [0, 2, 6],
        [0, 6, 4],
        [1, 5, 7],
        [1, 7, 3],
    ]
    base = len(floor_v)
    vertices = np.concatenate([floor_v, corners]).astype(np.float32)
    indices = np.concatenate([np.array(quads), np.array(faces) + base]).astype(np.int32)
    return vertices, indices


def rays_towards_floor(count: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Rays from above aimed at random floor points (some hit the box, a few miss)."""
    rng = np.random.default_rng(seed)
    origins = np.tile(np.array([[0.2, 2.0, 1.5]], np.float32), (count, 1))
    targets = rng.uniform(-1.2, 1.2, size=(count, 3)).astype(np.float32)
    targets[:, 1] = 0.0
    return origins, (targets - origins).astype(np.float32)


def scene_body(vertices: np.ndarray, indices: np.ndarray) -> bytes:
    return vertices.astype("<f4").tobytes() + indices.astype("<i4").tobytes()


def ray_body(origins: np.ndarray, directions: np.ndarray) -> bytes:
    return np.concatenate([origins, directions], axis=1).astype("<f4").tobytes()


OCTET = {"Content-Type": "application/octet-stream"}


class Api:
    """httpx against one service, with the binary encodings done once here."""

    def __init__(self, service: Service, timeout: float = 120.0) -> None:
        self.url = service.url
        self.client = httpx.Client(base_url=self.url, timeout=timeout, headers=service.auth)

    def upload(self, vertices: np.ndarray, indices: np.ndarray,
               normals: np.ndarray | None = None,
               terminator_offsets: np.ndarray | None = None) -> httpx.Response:
        """POST /v1/scenes, with the optional normal and terminator blocks when given."""
        params = {"vertices": len(vertices), "triangles": len(indices)}
        content = scene_body(vertices, indices)
        for name, block in (("normals", normals), ("terminator_offsets", terminator_offsets)):
            if block is not None:
                params[name] = "true"
                content += np.asarray(block, "<f4").tobytes()
        return self.client.post("/v1/scenes", params=params, content=content, headers=OCTET)

    def ao(
        self, scene_id: str, origins: np.ndarray, directions: np.ndarray, **params: object
    ) -> httpx.Response:
        return self.client.post(
            f"/v1/scenes/{scene_id}/ao",
            params={"rays": len(origins), **params},
            content=ray_body(origins, directions),
            headers=OCTET,
        )

    def health(self) -> httpx.Response:
        return self.client.get("/v1/health")


FINAL = frozenset({"done", "failed", "cancelled"})


def job_ended(client: httpx.Client, job_id: str, states: frozenset[str] = FINAL,
              timeout_s: float = WAIT_S) -> dict:
    """The job's status once its state is in `states` (by default: final), polled."""
    def reached() -> dict | None:
        status = client.get(f"/v1/jobs/{job_id}").json()
        return status if status["state"] in states else None

    return until(reached, f"job {job_id} to reach {sorted(states)}", timeout_s)


# --- fixtures -----------------------------------------------------------------------


@pytest.fixture(scope="session")
def start_service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Callable[..., Service]]:
    """Start a service with extra `serve` arguments (and, for the child, environment
    changes and a function run before exec); every one is stopped at session end."""
    started: list[Service] = []

    def start(
        *args: str, env: dict[str, str | None] | None = None,
        preexec_fn: Callable[[], None] | None = None,
    ) -> Service:
        log_path = tmp_path_factory.mktemp("service") / "stderr.log"
        service = launch(args, log_path, env, preexec_fn)
        started.append(service)
        return service

    yield start
    for service in started:
        stop(service)


@pytest.fixture(scope="session")
def service(start_service: Callable[..., Service]) -> Service:
    """The shared service (device cpu, default limits except a 64 MB body limit)."""
    return start_service("--max-body-mb", "64")


@pytest.fixture(scope="session")
def api(service: Service) -> Iterator[Api]:
    """A client of the shared service."""
    client = Api(service)
    yield client
    client.client.close()
