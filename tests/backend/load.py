"""A mixed load on a running service: clients sending every kind of request while renders
run, counting what came back. Used by tests/backend/test_service_load.py (a few seconds)
and benchmarks/service_load.py (32 clients for 60 s, with the latency figures).

Each request kind has the statuses it is designed to get; 429 and 503 (with Retry-After)
are the designed answers to overload; anything else is an error. The /v1/health latency
is measured by a probe in a process of its own (as a monitor would see it): the load
clients share one event loop, so their own timings include their queueing.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import multiprocessing
import random
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np

OCTET = {"Content-Type": "application/octet-stream"}
OVERLOAD = frozenset({429, 503})
TOP = [[1, 0, 0, 0], [0, 0, 1, 3], [0, -1, 0, 0], [0, 0, 0, 1]]  # 3 above the floor, down


@dataclass
class LoadReport:
    statuses: Counter[tuple[str, int]] = field(default_factory=Counter)
    errors: list[str] = field(default_factory=list)
    health_ms: list[float] = field(default_factory=list)  # the probe's
    client_health_ms: list[float] = field(default_factory=list)  # the load clients'
    rss_mb: list[float] = field(default_factory=list)
    renders: int = 0  # background renders finished

    @property
    def requests(self) -> int:
        return sum(self.statuses.values())

    def percentile_ms(self, q: float, which: str = "health_ms") -> float:
        values = getattr(self, which)
        return float(np.percentile(values, q)) if values else float("nan")


def rss_mb(pid: int) -> float:
    """Resident memory of a process (Linux /proc), in MiB."""
    status = Path(f"/proc/{pid}/status").read_text()
    return int(status.split("VmRSS:")[1].split()[0]) / 1024


def probe_health(url: str, seconds: float, every_s: float = 0.02) -> list[float]:
    """Milliseconds of each GET /v1/health, one every `every_s`, for `seconds`."""
    latencies = []
    with httpx.Client(base_url=url, timeout=30) as client:
        stop_at = time.monotonic() + seconds
        while time.monotonic() < stop_at:
            t0 = time.perf_counter()
            if client.get("/v1/health").status_code == 200:
                latencies.append(1e3 * (time.perf_counter() - t0))
            time.sleep(every_s)
    return latencies


def _scene(seed: int) -> tuple[bytes, int, int]:
    """A small random scene (its own content hash): body, vertices, triangles."""
    rng = np.random.default_rng(seed)
    vertices = rng.uniform(-1, 1, (30, 3)).astype("<f4")
    indices = rng.integers(0, 30, (40, 3)).astype("<i4")
    return vertices.tobytes() + indices.tobytes(), 30, 40


def _rays(count: int, seed: int) -> bytes:
    rng = np.random.default_rng(seed)
    origins = np.tile(np.float32([[0.2, 2.0, 1.5]]), (count, 1))
    targets = rng.uniform(-1.2, 1.2, (count, 3)).astype(np.float32)
    targets[:, 1] = 0
    return np.concatenate([origins, targets - origins], axis=1).astype("<f4").tobytes()


class Load:
    """`clients` coroutines on one service for `seconds`, plus one render always running."""

    def __init__(self, url: str, auth: dict[str, str], scene_id: str, pid: int) -> None:
        self.url, self.auth, self.scene_id, self.pid = url, auth, scene_id, pid
        self.report = LoadReport()

    def _count(self, kind: str, response: httpx.Response, designed: set[int]) -> int:
        status = response.status_code
        self.report.statuses[(kind, status)] += 1
        if status in OVERLOAD and "retry-after" not in response.headers:
            self.report.errors.append(f"{kind}: {status} without Retry-After")
        elif status not in designed | OVERLOAD:
            self.report.errors.append(f"{kind}: {status} {response.text[:200]}")
        return status

    async def _one(self, client: httpx.AsyncClient, rng: random.Random, k: int) -> None:
        sid, kind = self.scene_id, rng.choices(KINDS, WEIGHTS)[0]
        if kind == "health":
            t0 = time.perf_counter()
            response = await client.get("/v1/health")
            self.report.client_health_ms.append(1e3 * (time.perf_counter() - t0))
            self._count(kind, response, {200})
        elif kind == "head":
            self._count(kind, await client.head(f"/v1/scenes/{sid}"), {200})
        elif kind == "etag":
            response = await client.get(f"/v1/scenes/{sid}", headers={"If-None-Match": f'"{sid}"'})
            self._count(kind, response, {304})
        elif kind == "upload":
            body, v, t = _scene(rng.randrange(2**31))
            response = await client.post("/v1/scenes", params={"vertices": v, "triangles": t},
                                         content=body, headers=OCTET)
            self._count(kind, response, {200, 201})
        elif kind == "bvh":
            spec = {"method": rng.choice(["sah", "median"]), "leaf_size": rng.choice([4, 8])}
            self._count(kind, await client.post(f"/v1/scenes/{sid}/bvh", json=spec), {200})
        elif kind == "ao":
            response = await client.post(f"/v1/scenes/{sid}/ao", params={"rays": 256, "spp": 8},
                                         content=_rays(256, k), headers=OCTET)
            self._count(kind, response, {200})
        elif kind == "job":
            await self._job(client, rng)
        elif kind == "hostile":
            bad = rng.choice([({"Authorization": "Bearer wrong"}, 401),
                              ({"Host": "evil.example"}, 403),
                              ({"Origin": "http://evil.example"}, 403)])
            response = await client.get(f"/v1/scenes/{sid}", headers=bad[0])
            self._count(kind, response, {bad[1]})

    async def _job(self, client: httpx.AsyncClient, rng: random.Random) -> None:
        camera = {"matrix_world": TOP, "width": 32, "height": 24}
        created = await client.post("/v1/jobs", json={"scene_id": self.scene_id,
                                                     "camera": camera, "spp": 4})
        if self._count("job", created, {202}) != 202:
            return
        job_id = created.json()["job_id"]
        if rng.random() < 0.3:
            self._count("cancel", await client.delete(f"/v1/jobs/{job_id}"), {200})
            return
        for _ in range(2000):  # bounded: the render is 768 pixels
            status = await client.get(f"/v1/jobs/{job_id}")
            if self._count("poll", status, {200}) != 200:
                return
            if status.json()["state"] in ("done", "failed", "cancelled"):
                break
            await asyncio.sleep(0.02)
        if status.json()["state"] != "done":
            self.report.errors.append(f"job {job_id} ended {status.json()}")
            return
        self._count("result", await client.get(f"/v1/jobs/{job_id}/result"), {200})

    async def _client(self, k: int, stop_at: float) -> None:
        rng = random.Random(k)
        async with httpx.AsyncClient(base_url=self.url, headers=self.auth, timeout=60) as client:
            while time.monotonic() < stop_at:
                try:
                    await self._one(client, rng, k)
                except httpx.HTTPError as exc:
                    self.report.errors.append(f"transport: {type(exc).__name__}: {exc}")

    async def _renders(self, stop_at: float) -> None:
        """One 256x192 render at 64 spp after another, each followed to its end by events."""
        camera = {"matrix_world": TOP, "width": 256, "height": 192}
        async with httpx.AsyncClient(base_url=self.url, headers=self.auth, timeout=600) as client:
            while time.monotonic() < stop_at:
                created = await client.post("/v1/jobs", json={
                    "scene_id": self.scene_id, "camera": camera, "spp": 64})
                if self._count("render", created, {202}) != 202:
                    await asyncio.sleep(0.2)
                    continue
                job_id = created.json()["job_id"]
                async with client.stream("GET", f"/v1/jobs/{job_id}/events") as events:
                    if events.status_code != 200:
                        await events.aread()  # for the error's text
                    self._count("events", events, {200})
                    async for _ in events.aiter_lines():
                        if time.monotonic() > stop_at + 60:
                            break
                self.report.renders += 1

    async def _memory(self, stop_at: float) -> None:
        while time.monotonic() < stop_at:
            self.report.rss_mb.append(rss_mb(self.pid))
            await asyncio.sleep(0.1)

    def run(self, clients: int, seconds: float) -> LoadReport:
        async def main() -> None:
            stop_at = time.monotonic() + seconds
            await asyncio.gather(self._renders(stop_at), self._memory(stop_at),
                                 *(self._client(k, stop_at) for k in range(clients)))

        fork = multiprocessing.get_context("fork")  # before any thread of ours starts
        with concurrent.futures.ProcessPoolExecutor(1, mp_context=fork) as pool:
            probe = pool.submit(probe_health, self.url, seconds)
            asyncio.run(main())
            self.report.health_ms = probe.result(timeout=seconds + 60)
        return self.report


KINDS = ("health", "head", "etag", "upload", "bvh", "ao", "job", "hostile")
WEIGHTS = (4, 2, 2, 1, 1, 2, 2, 1)
