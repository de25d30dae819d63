"""Waiting for a condition, never for a length of time.

No test sleeps and hopes that something has happened by then. What a test can hold (a
thread, the device worker, the engine) it holds with an event and releases when it chooses
(tests/backend/gated.py). What happens in another process (a service starting, a job
ending, a log line being written) it waits FOR with `until`: the condition is polled until it
holds, and the test fails naming what it waited for if it never does within the bound.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")

WAIT_S = 60.0  # the default bound: long enough for a loaded machine, never reached when well


def until(condition: Callable[[], T], what: str, timeout_s: float = WAIT_S,
          every_s: float = 0.02) -> T:
    """The first truthy value of `condition()`, polled every `every_s`; AssertionError
    naming `what` (and the last value) once `timeout_s` has passed without one."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"waited {timeout_s:g} s for {what}; last: {value!r}")
        time.sleep(every_s)  # the poll interval: the condition decides, not this
