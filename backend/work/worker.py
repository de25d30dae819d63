"""One worker thread per device, draining a bounded queue.

A Warp CPU launch is one serial loop on one core (WARP_FACTS.md), and a device runs one
launch well at a time, so each device gets exactly one `DeviceWorker`. Short requests (BVH
build, AO on explicit rays) and long camera renders (`jobs.Job`) share its queue; the event
loop only awaits futures.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import threading
from collections import deque
from collections.abc import Callable
from typing import Any


class QueueFull(Exception):
    """The device queue is at capacity; the client should retry later (HTTP 429)."""


class DeviceWorker:
    """One thread that runs submitted callables in order on one device.

    The queue holds at most `max_queue` live tasks: a task whose future was cancelled
    before it started frees its slot at once."""

    def __init__(self, device: str, max_queue: int = 64) -> None:
        self.device = device
        self.max_queue = max_queue
        self._pending: deque[tuple[concurrent.futures.Future, Callable[[], Any]] | None]
        self._pending = deque()
        self._ready = threading.Condition()
        self._thread = threading.Thread(target=self._loop, name=f"worker-{device}", daemon=True)
        self._thread.start()

    def submit(self, fn: Callable[[], Any]) -> concurrent.futures.Future:
        """Queue `fn`; its future resolves with its result or exception. Raise QueueFull."""
        future: concurrent.futures.Future = concurrent.futures.Future()
        with self._ready:
            if self._live() >= self.max_queue:
                raise QueueFull(f"{self.max_queue} tasks already queued")
            self._pending.append((future, fn))
            self._ready.notify()
        return future

    async def run(self, fn: Callable[[], Any]) -> Any:
        """Submit `fn` and await its result from the event loop."""
        return await asyncio.wrap_future(self.submit(fn))

    def _live(self) -> int:
        """Queued tasks not cancelled (lock held); drops the cancelled ones."""
        kept = [item for item in self._pending if item is None or not item[0].cancelled()]
        if len(kept) != len(self._pending):
            self._pending = deque(kept)
        return len(kept)

    @property
    def queued(self) -> int:
        with self._ready:
            return self._live()

    def stop(self, timeout: float = 5.0) -> bool:
        """Cancel what is queued, let the running task end, stop the thread (bounded
        wait; it is a daemon). True if the thread ended within `timeout`."""
        with self._ready:
            for item in self._pending:
                if item is not None:
                    item[0].cancel()
            self._pending = deque([None])
            self._ready.notify()
        self._thread.join(timeout)
        return not self._thread.is_alive()

    def _loop(self) -> None:
        while True:
            with self._ready:
                while not self._pending:
                    self._ready.wait()
                item = self._pending.popleft()
            if item is None:
                return
            future, fn = item
            if not future.set_running_or_notify_cancel():
                continue
            try:
                future.set_result(fn())
            except BaseException as exc:  # noqa: BLE001 - the future carries it to the caller
                future.set_exception(exc)
