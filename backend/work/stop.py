"""How work learns it must stop: a flag with its reason (cancel, the client gone, the
service stopping) and a deadline, checked by the work between the engine's rounds."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field


class Stopped(Exception):
    """Work stopped before its end; the message says why (cancelled, past its deadline,
    the service stopping). Raised inside the work at its next progress report."""


@dataclass(eq=False)  # compared and hashed by identity: kept in a set of live work
class StopSignal:
    """How work learns it must stop: a flag with its reason, and a deadline."""

    deadline: float = float("inf")  # time.monotonic() after which the work fails
    reason: str | None = None
    _flag: threading.Event = field(default_factory=threading.Event, repr=False)

    def stop(self, reason: str) -> None:
        if not self._flag.is_set():
            self.reason = reason
            self._flag.set()

    @property
    def stopped(self) -> bool:
        return self._flag.is_set()

    def check(self) -> None:
        """Raise Stopped if the work should end now (called between the engine's rounds)."""
        if self._flag.is_set():
            raise Stopped(self.reason or "cancelled")
        if time.monotonic() > self.deadline:
            raise Stopped("past the deadline (serve --max-seconds)")
