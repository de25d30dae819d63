"""The persistent worker of the 2012 paper (Algorithm 1, sec. 3.3-3.4), written once for
every pool application, and its launch.

A worker loops until no task is left: it acquires work chunks of an active task's current
step (`pool_acquire`), runs them, reports them finished, and the last finisher of a step
advances the task: it interprets the step's results, and runs the following steps inline
while they have fewer than K chunks (sec. 3.4), finishing tasks and continuing with a child
or an activated dependant, until a step is big enough to hand to the pool. A worker that
finds no work waits (`pool_idle`), and declares the pool stuck after a while without work
(pool.state.WAIT_SECONDS). Each worker counts the ticks of the pool's clock (pool.clock) per
phase in its own row of `phase_cycles`: running a phase's chunks and completing its steps go
to that phase, finishing a task to the application's `done` phase. Only their ratios are
used (the host shares a launch's time out by them), so the clock's rate does not matter.

An application (`Application`) supplies its data struct, its task struct and three Warp
functions; `make_worker` generates the worker kernel from them, compiled in the
application's own Warp module, so the application's functions are called directly (no
indirection: they inline as if written in place). docs/architecture.md shows how to add an
application.

Here a worker is one thread (the paper's warp of 32 threads shares a chunk of 32 items; one
thread walks the chunk's items instead). On CPU each worker is a launch of its own, from a
host thread of its own, so that the workers run in parallel.
"""

# No `from __future__ import annotations`: the generated functions' annotations must be the
# application's types (closure variables), not strings.

from dataclasses import dataclass
from typing import Any

import warp as wp

from ..core.launch import host_pool
from .clock import ticks
from .state import (
    Pool,
    pool_acquire,
    pool_finish,
    pool_hand_over,
    pool_idle,
    pool_running,
)

CYCLE_ROW = wp.constant(16)  # int64 per worker in phase_cycles (ticks): two cache lines, no sharing


@dataclass(frozen=True)
class Application:
    """What a pool application plugs into the worker.

    data: a `@wp.struct` with `tasks` (an array of `task`, one per pool slot) and
        `phase_cycles` (int64, CYCLE_ROW per worker), and whatever else the steps need.
    task: a `@wp.struct` with `phase` (< CYCLE_ROW) and `chunks` (of the current step).
    run_chunks(data, worker, slot, task, first, count): run chunks first ..
        first + count - 1 of the task's current step (`worker`: this worker's index, for
        what a worker keeps of its own; the pool itself is not for chunks to touch).
    complete_step(data, task, slot) -> task: the last finisher's work at the end of a
        step: the next step (its `phase` and `chunks`), or phase `done`.
    finish_task(data, pool, worker, task, slot) -> int: a task in phase `done`: store its
        children or activate its dependants, release or reuse its slot; return a locked
        slot whose task this worker continues with (its data in `data.tasks`), or -1.
    done: the phase of a finished task (its ticks: the time spent finishing tasks).
    module: the Warp module to compile the worker in: the application's (`__name__`).
    name: a prefix for the generated kernel and functions.
    """

    data: Any
    task: Any
    run_chunks: Any
    complete_step: Any
    finish_task: Any
    done: int
    module: str
    name: str


def make_worker(app: Application) -> wp.Kernel:
    """The worker kernel of `app`: launch it with (data, pool, first worker index)
    through `launch_workers`."""
    Data, Task = app.data, app.task  # noqa: N806 (types, in the annotations below)
    run_chunks, complete_step, finish_task = app.run_chunks, app.complete_step, app.finish_task
    done = int(app.done)

    def add_ticks(d: Data, worker: int, phase: int, since: wp.int64):
        i = worker * CYCLE_ROW + phase
        d.phase_cycles[i] = d.phase_cycles[i] + (ticks() - since)

    add_ticks = wp.func(add_ticks, module=app.module, name=f"{app.name}_add_ticks")

    def advance(d: Data, pool: Pool, worker: int, slot: int, t: Task):
        """The last finisher of a step: complete it, run the following steps inline while
        they have fewer than K chunks (sec. 3.4), finishing tasks and continuing with the
        slot `finish_task` returns; publish the first step big enough for the pool."""
        s = slot
        task = t
        while True:
            phase = task.phase
            since = ticks()
            task = complete_step(d, task, s)
            add_ticks(d, worker, phase, since)
            if task.phase == done:
                since = ticks()
                next_slot = finish_task(d, pool, worker, task, s)
                add_ticks(d, worker, done, since)
                if next_slot < 0:
                    return
                s = next_slot
                task = d.tasks[s]
            if task.chunks >= pool.min_chunks:
                d.tasks[s] = task
                pool_hand_over(pool, s, task.chunks)
                return
            since = ticks()
            run_chunks(d, worker, s, task, 0, task.chunks)
            add_ticks(d, worker, task.phase, since)

    advance = wp.func(advance, module=app.module, name=f"{app.name}_advance")

    def worker_kernel(d: Data, pool: Pool, first_worker: int):
        """Algorithm 1: acquire chunks, run them, finish them; the last finisher advances."""
        worker = first_worker + wp.tid()
        idle_since = wp.int64(-1)
        while pool_running(pool):
            got = pool_acquire(pool)
            slot = got[0]
            if slot < 0:
                idle_since = pool_idle(pool, idle_since)
                continue
            idle_since = wp.int64(-1)
            t = d.tasks[slot]
            since = ticks()
            run_chunks(d, worker, slot, t, got[1], got[2])
            add_ticks(d, worker, t.phase, since)
            if pool_finish(pool, slot, got[2]):
                advance(d, pool, worker, slot, d.tasks[slot])

    return wp.kernel(worker_kernel, module=app.module, name=f"{app.name}_worker",
                     enable_backward=False)


def launch_workers(kernel, workers: int, inputs: list, device) -> None:
    """Launch a persistent worker kernel whose last argument is the first worker's index:
    on CPU one launch of one worker per host thread, so the workers run in parallel."""
    if not wp.get_device(device).is_cpu or workers == 1:
        wp.launch(kernel, dim=workers, inputs=[*inputs, 0], device=device)
        return
    wp.load_module(kernel.module, device=device)
    futures = [
        host_pool(workers).submit(wp.launch, kernel, dim=1, inputs=[*inputs, w], device=device)
        for w in range(workers)
    ]
    for f in futures:
        f.result()
