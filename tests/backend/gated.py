"""The service in this process with a gated engine: races a test decides, not the clock.

`serve(app)` runs an app of `create_app` under the service's own uvicorn server
(api/server.py) on 127.0.0.1 in a thread: real HTTP, with the app's `Service` (its store,
device worker, jobs and work in flight) in reach of the test. `GatedEngine` stands in for
`kernels.render_ao`, which every AO request and camera job ends in: each call announces
itself, then waits for `release()` before its first round, which is where the work checks
its stop signal (cancel, hang-up, deadline), and renders for real after it. So a test
knows that a job or request IS running, holds it there while it cancels, hangs up or asks
for a result, and lets it go when it chooses. tests/backend/test_gated_work.py and
test_service_concurrency.py use it; the same behaviours also have one end-to-end test each
against a `scenesort serve` process with the real engine (test_service_jobs.py,
test_hostile.py).
"""

from __future__ import annotations

import contextlib
import queue
import socket
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import httpx
import pytest
from fastapi import FastAPI
from scenesort.backend.api.app import create_app
from scenesort.backend.api.server import server
from scenesort.backend.api.service import Service, Settings
from scenesort.backend.commands.serve import _listen

from scenesort import kernels
from tests.waiting import WAIT_S, until


class GatedEngine:
    """`kernels.render_ao`, held before its first round until `release()`.

    `entered` gets one item per call as it starts (the work is then provably running on
    the device worker); `passed` counts the calls let through; `rounds` the calls that
    went on to render after the stop check."""

    def __init__(self, real: Callable[..., Any]) -> None:
        self.real = real
        self.entered: queue.Queue[int] = queue.Queue()
        self.calls = self.passed = self.rounds = 0
        self._gate = threading.Event()

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        self.calls += 1
        self.entered.put(self.calls)
        if not self._gate.wait(WAIT_S):
            raise AssertionError(f"the test never released the engine in {WAIT_S:g} s")
        self.passed += 1
        progress = kwargs.get("progress")
        if progress is not None:
            progress(0.0, "occlusion")  # the round boundary: raises Stopped if told to stop
        self.rounds += 1
        return self.real(*args, **kwargs)

    def wait_entered(self) -> int:
        """Block until a call has entered the engine; its number (1, 2, ...)."""
        try:
            return self.entered.get(timeout=WAIT_S)
        except queue.Empty:
            raise AssertionError(f"nothing entered the engine in {WAIT_S:g} s") from None

    def release(self) -> None:
        """Let every held call, and every later one, through."""
        self._gate.set()


@dataclass
class Running:
    """A service served in this process: its URL, a client and its shared state."""

    url: str
    client: httpx.Client
    service: Service

    def wait_idle(self) -> None:
        """Until the device worker has run everything queued before this call: it runs
        its tasks in order, so a no-op's result means they are done."""
        self.service.worker.submit(lambda: None).result(timeout=WAIT_S)

    def host_port(self) -> tuple[str, int]:
        host, port = self.url.removeprefix("http://").rsplit(":", 1)
        return host, int(port)


@contextlib.contextmanager
def serve(app: FastAPI) -> Iterator[Running]:
    """`app` (made by `create_app`) served on an ephemeral port until the block ends."""
    sock = _listen(socket.AF_INET, "127.0.0.1", 0)
    uv = server(app, log_level="warning")
    thread = threading.Thread(target=uv.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    url = f"http://127.0.0.1:{sock.getsockname()[1]}"
    running = Running(url, httpx.Client(base_url=url, timeout=WAIT_S), app.state.service)
    try:
        until(lambda: uv.started or not thread.is_alive(), "uvicorn to start")
        assert thread.is_alive(), "uvicorn stopped while starting"
        running.wait_idle()  # the engine's warm-up (the app's startup) is done
        yield running
    finally:
        running.client.close()
        uv.should_exit = True
        thread.join(timeout=WAIT_S)
        sock.close()


@pytest.fixture(scope="module")
def inproc() -> Iterator[Running]:
    """One in-process service (default settings, no token) for a test module."""
    with serve(create_app(Settings())) as running:
        yield running


@pytest.fixture
def gate(inproc: Running, monkeypatch: pytest.MonkeyPatch) -> Iterator[GatedEngine]:
    """The engine of `inproc` held at its first round for this test; released at its end,
    and the worker left idle for the next test."""
    gated = GatedEngine(kernels.render_ao)
    monkeypatch.setattr(kernels, "render_ao", gated)
    try:
        yield gated
    finally:
        gated.release()
        inproc.wait_idle()
