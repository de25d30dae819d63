"""Work chunks and the 32-ary reduction trees that the pool applications build over them.

A step over n items has ceil(n / CHUNK) work chunks. A reduction (PPS, AABB) over a range
[base, base + n) has levels 1..level_count(n): level 1 holds one value per chunk, each
level above one value per CHUNK values below, the top a single value. The levels are packed
one after the other inside the range itself, which always has room for them.
"""

from __future__ import annotations

import warp as wp

CHUNK = wp.constant(32)  # items per work chunk (the paper's warp width)


@wp.func
def ceil_div(a: int, b: int) -> int:
    return (a + b - 1) / b


@wp.func
def level_count(n: int) -> int:
    """Levels of the reduction tree over n items."""
    levels = int(1)
    s = ceil_div(n, CHUNK)
    while s > 1:
        s = ceil_div(s, CHUNK)
        levels += 1
    return levels


@wp.func
def level_size(n: int, level: int) -> int:
    """Values at `level` (level 0 is the n items themselves)."""
    s = n
    for _ in range(level):
        s = ceil_div(s, CHUNK)
    return s


@wp.func
def level_base(base: int, n: int, level: int) -> int:
    """Where `level` (>= 1) of the reduction over [base, base + n) is stored."""
    off = base
    s = n
    for _ in range(level - 1):
        s = ceil_div(s, CHUNK)
        off += s
    return off
