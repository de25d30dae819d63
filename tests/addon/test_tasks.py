"""Tasks run inline or on a thread, record their steps, and stop at a step once cancelled."""

from __future__ import annotations

import threading

import pytest

from addon.tasks import Cancelled, Task


def test_inline_run_returns_the_result_and_steps() -> None:
    def body(task: Task) -> int:
        task.set_step("one")
        task.set_step("two")
        return 7

    task = Task(body)
    assert task.run() == 7 and task.steps == ["one", "two"] and task.step == "two"


def test_thread_hands_errors_to_the_caller() -> None:
    task = Task(lambda t: 1 / 0)
    task.start()
    task._thread.join(10)
    assert task.done and isinstance(task.error, ZeroDivisionError)


def test_cancel_stops_at_the_next_step() -> None:
    started, release = threading.Event(), threading.Event()
    reached: list[str] = []

    def body(task: Task) -> None:
        task.set_step("waiting")
        started.set()
        release.wait(10)
        task.set_step("after cancel")  # raises Cancelled
        reached.append("end")

    task = Task(body)
    task.start()
    assert started.wait(10)
    task.cancel()
    release.set()
    task._thread.join(10)
    assert task.done and isinstance(task.error, Cancelled) and reached == []
    assert task.steps == ["waiting"]
    with pytest.raises(Cancelled):  # a cancelled task also refuses steps run inline
        task.set_step("x")
