"""The seven-children dependency look-up table of task-pool DACRT (2012 paper, sec. 5.3).

A split sorts a task's rays and triangles into three intervals each: near, straddling, far
(the paper's left, straddling, right; the kernel maps left/right to near/far by the rays'
main direction, so that straddling rays meet near triangles before far ones). Seven of the
nine ray/triangle interval pairs can intersect; each becomes a child task:

    T1 (near, near)   T2 (near, straddling)   T3 (straddling, near)   T4 (straddling, straddling)
    T5 (straddling, far)   T6 (far, straddling)   T7 (far, far)          (rays, triangles)

with the dependency groups (T1, T4, T7), (T2, T3), (T5, T6) and the edges of sec. 5.3. Tasks
with an empty interval are dropped; their predecessors then activate their successors
directly (the order restricted to the remaining tasks, transitively reduced). The table is
indexed by a 6-bit mask: bit i set when ray interval i is empty, bit 3 + j when triangle
interval j is empty. Plain numpy, shared by the kernel (`flat_table`) and its exhaustive test.
"""

from __future__ import annotations

import functools

import numpy as np

NEAR, STRADDLE, FAR = 0, 1, 2
TASKS = 7
MASKS = 64
# (ray interval, triangle interval) of T1..T7
RAY_INTERVAL = np.array([NEAR, NEAR, STRADDLE, STRADDLE, STRADDLE, FAR, FAR], np.int32)
TRI_INTERVAL = np.array([NEAR, STRADDLE, NEAR, STRADDLE, FAR, STRADDLE, FAR], np.int32)
# sec. 5.3: TX -> TY means TX activates TY (0-based: T1 is 0)
EDGES = ((0, 1), (0, 2), (3, 1), (3, 2), (6, 4), (6, 5), (2, 4), (1, 5))
MAX_SUCC = 2  # each task activates at most two siblings (checked by the test)

# Row layout of the flat table, one row per mask.
COUNT = 0  # child tasks to create
SINKS = 1  # tasks of the last dependency group: they inherit the parent's dependants
ORDER = 2  # TASKS entries: task ids in insertion order (successors first), -1 padded
PREDS = ORDER + TASKS  # TASKS entries per task id: dependencies (0 = active at once)
IS_SINK = PREDS + TASKS  # TASKS entries per task id
SUCC = IS_SINK + TASKS  # TASKS * MAX_SUCC entries per task id, -1 padded
ROW = SUCC + TASKS * MAX_SUCC


def _closure() -> np.ndarray:
    """reach[x, y]: y depends on x through the full seven-task graph."""
    reach = np.zeros((TASKS, TASKS), dtype=bool)
    for x, y in EDGES:
        reach[x, y] = True
    for k in range(TASKS):
        reach |= reach[:, [k]] & reach[[k], :]
    return reach


def present_tasks(mask: int) -> np.ndarray:
    """Task ids whose ray and triangle intervals are both non-empty under `mask`."""
    ray_empty = [(mask >> i) & 1 for i in range(3)]
    tri_empty = [(mask >> (3 + j)) & 1 for j in range(3)]
    return np.array([t for t in range(TASKS)
                     if not ray_empty[RAY_INTERVAL[t]] and not tri_empty[TRI_INTERVAL[t]]],
                    dtype=np.int32)


def entry(mask: int) -> dict:
    """One table entry: the remaining tasks, their reduced edges, order and sinks."""
    tasks = [int(t) for t in present_tasks(mask)]
    reach = _closure()
    edges = []
    for x in tasks:
        for y in tasks:
            # keep x -> y unless a remaining task z lies between them (transitive reduction)
            if reach[x, y] and not any(reach[x, z] and reach[z, y] for z in tasks):
                edges.append((x, y))
    succ = {t: [y for x, y in edges if x == t] for t in tasks}
    preds = {t: sum(1 for _, y in edges if y == t) for t in tasks}
    sinks = [t for t in tasks if not succ[t]]
    # successors first: a task must exist before the task that activates it (sec. 5.3)
    depth = {t: 0 for t in tasks}
    for _ in tasks:
        for x, y in edges:
            depth[y] = max(depth[y], depth[x] + 1)
    order = sorted(tasks, key=lambda t: (-depth[t], t))
    return {"tasks": tasks, "edges": edges, "succ": succ, "preds": preds, "sinks": sinks,
            "order": order}


@functools.cache
def flat_table() -> np.ndarray:
    """All 64 entries as one int32 array of MASKS * ROW values (layout above); made once
    (read-only)."""
    table = np.full((MASKS, ROW), -1, dtype=np.int32)
    for mask in range(MASKS):
        e = entry(mask)
        row = table[mask]
        row[COUNT] = len(e["tasks"])
        row[SINKS] = len(e["sinks"])
        row[PREDS:PREDS + TASKS] = 0
        row[IS_SINK:IS_SINK + TASKS] = 0
        for i, t in enumerate(e["order"]):
            row[ORDER + i] = t
        for t in e["tasks"]:
            row[PREDS + t] = e["preds"][t]
            row[IS_SINK + t] = int(t in e["sinks"])
            if len(e["succ"][t]) > MAX_SUCC:
                raise AssertionError(f"task {t} of mask {mask} activates > {MAX_SUCC} tasks")
            for k, y in enumerate(e["succ"][t]):
                row[SUCC + t * MAX_SUCC + k] = y
    flat = table.reshape(-1)
    flat.flags.writeable = False
    return flat
