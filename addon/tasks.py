"""Work that runs to completion on the main thread (execute) or on a worker thread (invoke).

Blender data is read before the task starts and written after it ends, always on
the main thread; the task body only does HTTP and numpy, so it is safe in a thread.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterator
from typing import Any


def _start(callback: Callable[[], Any]) -> None:
    threading.Thread(target=callback, name="scenesort-cancel", daemon=True).start()


class Cancelled(Exception):
    """The user pressed Esc; the task stopped at its next step."""


class Task:
    """One unit of work with a progress line and cooperative cancelling between steps."""

    def __init__(self, body: Callable[[Task], Any]) -> None:
        self._body = body
        self._cancel = threading.Event()
        self._on_cancel: list[Callable[[], Any]] = []
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self.step = "starting"
        self.steps: list[str] = []  # every step so far, oldest first
        self.fraction = 0.0  # how far the work is, 0..1, where a step says
        self.result: Any = None
        self.error: BaseException | None = None

    def set_step(self, text: str, fraction: float | None = None) -> None:
        """Name the current step (shown in the status bar), and how far the work is if
        known; stop here if cancelled."""
        if self._cancel.is_set():
            raise Cancelled()
        self.step = text
        self.steps.append(text)
        if fraction is not None:
            self.fraction = fraction

    def cancel(self) -> None:
        """Stop at the next step, and run the callbacks of `cancelling` blocks (each on a
        thread of its own: the caller, Blender's main thread, never waits on them)."""
        with self._lock:
            self._cancel.set()
            callbacks, self._on_cancel = self._on_cancel, []
        for callback in callbacks:
            _start(callback)

    @contextlib.contextmanager
    def cancelling(self, callback: Callable[[], Any]) -> Iterator[None]:
        """Within the block, a cancel also runs `callback` (at once if the task already is
        cancelled): what the body waits on between steps, such as a service job it
        long-polls, stops then rather than at the body's next look."""
        with self._lock:
            cancelled = self._cancel.is_set()
            if not cancelled:
                self._on_cancel.append(callback)
        if cancelled:
            _start(callback)
        try:
            yield
        finally:
            with self._lock:
                if callback in self._on_cancel:
                    self._on_cancel.remove(callback)

    @property
    def cancelled(self) -> bool:
        return self._cancel.is_set()

    def run(self) -> Any:
        """Run in the calling thread; exceptions propagate."""
        self.result = self._body(self)
        return self.result

    def _run_caught(self) -> None:
        try:
            self.run()
        except BaseException as exc:  # handed to the main thread, which reports it
            self.error = exc

    def start(self) -> None:
        """Run on a daemon thread: a hung request must not keep Blender from quitting."""
        self._thread = threading.Thread(target=self._run_caught, name="scenesort", daemon=True)
        self._thread.start()

    def join(self, timeout: float | None = None) -> None:
        """Wait for a started task's thread to end."""
        if self._thread is not None:
            self._thread.join(timeout)

    @property
    def done(self) -> bool:
        return self._thread is not None and not self._thread.is_alive()
