"""The chunk phases that pool applications share (2012 paper, sec. 4.1): PPS, a 32-ary
parallel prefix sum of marks; Swap, which moves a segment's marked items behind its pivot;
AABB, a 32-ary reduction of boxes.

Each function does one work chunk of one segment [base, base + n) of an application's
arrays; the levels of the reduction trees are packed inside the segment (`chunks.py`). A
phase over several segments runs their chunks one after another (see `dacrt.task_pool`).
Level 1 is the application's own: PPS level 1 marks a chunk's items (which items go behind
the pivot is the application's rule) and stores their count with `pps_count`; AABB level 1
takes a chunk's box from its items and stores it with `store_box`. Everything above level
1, and all of Swap, is here.

Swap moves whole items (`wp.array(dtype=Any)`: a triangle id, or an id with its box): step
0 gathers the unmarked items behind the pivot into a spare array, ranked, with the position
each came from; step 1 trades them for the marked items in front of the pivot.
"""

from __future__ import annotations

from typing import Any

import warp as wp

from ..core.box import INF, max3, min3
from .chunks import CHUNK, ceil_div, level_base, level_count, level_size

# ---------------------------------------------------------------- PPS


@wp.func
def pps_chunks(n: int, levels: int, top: int, step: int) -> int:
    """Chunks of a segment of n items (`levels` = level_count(n)) at PPS step `step`, in a
    phase whose tallest segment has `top` levels: the up-sweep of level step + 1 while
    step < levels, then down-sweeps aligned so that every segment ends at step 2 top - 2."""
    if step < levels:
        return level_size(n, step + 1)
    if step >= top:
        level = 2 * top - 1 - step
        if level <= levels - 1:
            return level_size(n, level + 1)
    return 0


@wp.func
def pps_count(scan: wp.array(dtype=int), base: int, chunk: int, total: int):
    """Up-sweep, level 1: the marked items of one chunk (level 1 starts at `base`)."""
    scan[base + chunk] = total


@wp.func
def pps_up_chunk(scan: wp.array(dtype=int), base: int, n: int, level: int, chunk: int):
    """Up-sweep, level >= 2: the sum of CHUNK values of the level below."""
    src = level_base(base, n, level - 1)
    m = level_size(n, level - 1)
    total = int(0)
    for i in range(chunk * CHUNK, wp.min(chunk * CHUNK + CHUNK, m)):
        total += scan[src + i]
    scan[level_base(base, n, level) + chunk] = total


@wp.func
def pps_down_chunk(scan: wp.array(dtype=int), base: int, n: int, level: int, chunk: int):
    """Down-sweep: CHUNK sums of `level` become exclusive prefix sums, starting from the
    offset that the level above now holds for this group."""
    src = level_base(base, n, level)
    m = level_size(n, level)
    running = scan[level_base(base, n, level + 1) + chunk]
    for i in range(chunk * CHUNK, wp.min(chunk * CHUNK + CHUNK, m)):
        x = scan[src + i]
        scan[src + i] = running
        running += x


@wp.func
def pps_total(scan: wp.array(dtype=int), base: int, n: int) -> int:
    """After the up-sweep: the segment's marked items, held by the top of its tree, which
    becomes the 0 offset the down-sweep starts from."""
    top = level_base(base, n, level_count(n))
    total = scan[top]
    scan[top] = 0
    return total


@wp.func
def ones_before(scan: wp.array(dtype=int), mark: wp.array(dtype=wp.int8), base: int, n: int,
                local: int) -> int:
    """Marked items before local position `local` of a segment, from the PPS result."""
    c = local / CHUNK
    ones = int(0)
    if c < ceil_div(n, CHUNK):
        ones = scan[base + c]
    for i in range(base + c * CHUNK, base + local):
        ones += int(mark[i])
    return ones


# ---------------------------------------------------------------- Swap


@wp.func
def swap_chunks(n: int, pivot: int, step: int) -> int:
    """Chunks of a segment's Swap step: step 0 covers the chunks from the pivot's on, step 1
    those in front of the pivot."""
    if step == 0:
        return ceil_div(n, CHUNK) - pivot / CHUNK
    return ceil_div(pivot, CHUNK)


@wp.func
def swap_gather_chunk(items: wp.array(dtype=Any), spare: wp.array(dtype=Any),
                      spare_pos: wp.array(dtype=int), mark: wp.array(dtype=wp.int8),
                      scan: wp.array(dtype=int), base: int, n: int, pivot: int,
                      ones_left: int, chunk: int):
    """Swap, step 0: the unmarked items behind the pivot go to the spare array, ranked among
    themselves (`ones_left`: the marked items in front of the pivot)."""
    c = pivot / CHUNK + chunk
    ones = scan[base + c]
    zeros_left = pivot - ones_left
    for k in range(c * CHUNK, wp.min(c * CHUNK + CHUNK, n)):
        if mark[base + k] != wp.int8(0):
            ones += 1
        elif k >= pivot:
            r = base + (k - ones) - zeros_left
            spare[r] = items[base + k]
            spare_pos[r] = base + k


@wp.func
def swap_exchange_chunk(items: wp.array(dtype=Any), spare: wp.array(dtype=Any),
                        spare_pos: wp.array(dtype=int), mark: wp.array(dtype=wp.int8),
                        scan: wp.array(dtype=int), base: int, pivot: int, chunk: int):
    """Swap, step 1: the r-th marked item in front of the pivot trades places with the r-th
    item of the spare array."""
    ones = scan[base + chunk]
    for k in range(chunk * CHUNK, wp.min(chunk * CHUNK + CHUNK, pivot)):
        if mark[base + k] != wp.int8(0):
            i = base + k
            r = base + ones
            items[spare_pos[r]] = items[i]
            items[i] = spare[r]
            ones += 1


# ---------------------------------------------------------------- AABB


@wp.func
def aabb_chunks(n: int, level: int) -> int:
    """AABB chunks of a segment at `level`: none once it is reduced to one box."""
    if level > level_count(n):
        return 0
    return level_size(n, level)


@wp.func
def store_box(box_lo: wp.array(dtype=wp.vec3), box_hi: wp.array(dtype=wp.vec3), base: int,
              n: int, level: int, chunk: int, lo: wp.vec3, hi: wp.vec3):
    """The box of one chunk of `level` (level 1: of CHUNK items, from the application)."""
    dst = level_base(base, n, level) + chunk
    box_lo[dst] = lo
    box_hi[dst] = hi


@wp.func
def reduce_boxes(box_lo: wp.array(dtype=wp.vec3), box_hi: wp.array(dtype=wp.vec3), base: int,
                 n: int, level: int, chunk: int):
    """AABB, level >= 2: the union of CHUNK boxes of the level below."""
    src = level_base(base, n, level - 1)
    first = src + chunk * CHUNK
    lo = wp.vec3(INF)
    hi = wp.vec3(-INF)
    for i in range(first, wp.min(first + CHUNK, src + level_size(n, level - 1))):
        lo = min3(lo, box_lo[i])
        hi = max3(hi, box_hi[i])
    store_box(box_lo, box_hi, base, n, level, chunk, lo, hi)


@wp.func
def reduced_box(box_lo: wp.array(dtype=wp.vec3), box_hi: wp.array(dtype=wp.vec3), base: int,
                n: int) -> wp.mat33:
    """Rows 0, 1: the segment's box, the top of its reduction."""
    top = level_base(base, n, level_count(n))
    return wp.matrix_from_rows(box_lo[top], box_hi[top], wp.vec3(0.0))
