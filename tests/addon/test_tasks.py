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


def test_a_cancel_runs_the_cancelling_blocks_callback_at_once() -> None:
    """Within `cancelling`, cancel() runs the callback on a thread of its own while the body
    still waits (a long poll); one registered after the cancel runs at once; after the
    block a cancel no longer runs it."""
    called, inside, release = threading.Event(), threading.Event(), threading.Event()

    def body(task: Task) -> None:
        with task.cancelling(called.set):
            inside.set()
            release.wait(10)  # a poll that does not look at the task

    task = Task(body)
    task.start()
    assert inside.wait(10)
    task.cancel()
    assert called.wait(10) and not task.done  # the body is still in its wait
    release.set()
    task._thread.join(10)
    late = threading.Event()
    with task.cancelling(late.set):
        assert late.wait(10)
    after, idle = Task(lambda t: None), threading.Event()
    with after.cancelling(idle.set):
        pass
    after.cancel()
    assert not idle.wait(0.2)
