"""Exhaustive check of the seven-children dependency table (2012 paper, sec. 5.3)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scenesort.kernels.dacrt import table as tb

pytestmark = pytest.mark.host_only  # numpy

TABLE = tb.flat_table().reshape(tb.MASKS, tb.ROW)


def decode(mask: int):
    row = TABLE[mask]
    count = int(row[tb.COUNT])
    order = [int(t) for t in row[tb.ORDER:tb.ORDER + count]]
    succ = {t: [int(y) for y in row[tb.SUCC + t * tb.MAX_SUCC:tb.SUCC + (t + 1) * tb.MAX_SUCC]
                if y >= 0] for t in order}
    preds = {t: int(row[tb.PREDS + t]) for t in order}
    sinks = [t for t in order if row[tb.IS_SINK + t]]
    return order, succ, preds, sinks, int(row[tb.SINKS])


def reachability(order, succ) -> dict:
    reach = {t: set() for t in order}
    for _ in order:
        for t in order:
            for y in succ[t]:
                reach[t] |= {y} | reach[y]
    return reach


@pytest.mark.parametrize("mask", range(tb.MASKS))
def test_every_intersectable_pair_once_and_no_concurrent_sharing(mask):
    order, succ, preds, sinks, n_sinks = decode(mask)
    ray_empty = [(mask >> i) & 1 for i in range(3)]
    tri_empty = [(mask >> (3 + j)) & 1 for j in range(3)]
    # the pairs that can intersect: all but (near rays, far tris) and (far rays, near tris)
    wanted = sorted((r, t) for r, t in itertools.product(range(3), range(3))
                    if not ray_empty[r] and not tri_empty[t] and {r, t} != {tb.NEAR, tb.FAR})
    covered = sorted((int(tb.RAY_INTERVAL[k]), int(tb.TRI_INTERVAL[k])) for k in order)
    assert covered == wanted, "a pair is missing or covered twice"
    reach = reachability(order, succ)
    for a, b in itertools.combinations(order, 2):
        concurrent = b not in reach[a] and a not in reach[b]
        shares = (tb.RAY_INTERVAL[a] == tb.RAY_INTERVAL[b]
                  or tb.TRI_INTERVAL[a] == tb.TRI_INTERVAL[b])
        assert not (concurrent and shares), f"T{a + 1} and T{b + 1} may run together"


@pytest.mark.parametrize("mask", range(tb.MASKS))
def test_counts_order_and_inheritance_are_consistent(mask):
    order, succ, preds, sinks, n_sinks = decode(mask)
    assert len(set(order)) == len(order)
    assert n_sinks == len(sinks) == sum(1 for t in order if not succ[t])
    incoming = {t: 0 for t in order}
    for t in order:
        assert len(succ[t]) <= tb.MAX_SUCC
        for y in succ[t]:
            incoming[y] += 1
            assert order.index(y) < order.index(t), "a task is stored before its successor"
    assert incoming == preds
    # every task precedes some sink: when the sinks are done, the whole subtree is done and
    # the parent's dependants (inherited by the sinks) may start
    reach = reachability(order, succ)
    for t in order:
        assert t in sinks or any(s in reach[t] for s in sinks)
    # a serial run from the active tasks activates every task exactly once
    left = dict(preds)
    ready = [t for t in order if left[t] == 0]
    done = []
    while ready:
        t = ready.pop()
        done.append(t)
        for y in succ[t]:
            left[y] -= 1
            if left[y] == 0:
                ready.append(y)
    assert sorted(done) == sorted(order)


def test_full_entry_is_the_papers_table():
    order, succ, preds, sinks, _ = decode(0)
    assert {t + 1: sorted(y + 1 for y in s) for t, s in succ.items()} == {
        1: [2, 3], 2: [6], 3: [5], 4: [2, 3], 5: [], 6: [], 7: [5, 6]}
    assert sorted(t + 1 for t in order if preds[t] == 0) == [1, 4, 7]
    assert sorted(t + 1 for t in sinks) == [5, 6]
    assert np.all(TABLE[:, tb.COUNT] <= tb.TASKS)
