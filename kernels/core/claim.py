"""Chunks of one call's items, claimed by the host threads that share it
(`launch_claimed`): each thread's launch takes the next unclaimed chunk from a counter
until none is left, the pool's work claiming (2012 paper, sec. 3.3) at the scale of one
kernel call. A kernel item is a chunk of items, not one: Warp's CPU launch loop costs
about 12 ns a kernel item (measured: 10^6 cheap any-hit rays ran at 24.5 Mrays/s one ray a
kernel item, 35 Mrays/s 64 rays and more a kernel item).
"""

from __future__ import annotations

import functools

import numpy as np
import warp as wp

from .atomics import shared_add
from .compile_options import MODULE_OPTIONS
from .launch import launch_key, run_parts

wp.set_module_options(MODULE_OPTIONS)

CLAIMS_PER_THREAD = 32  # chunks per host thread, for load balance
MIN_CLAIM = 64  # fewest items a chunk: Warp's per-item cost amortised; a packet of 64 rays


@wp.struct
class Claims:
    """How a call's `count` items are shared: chunks of `chunk` items; `counter` holds the
    next unclaimed chunk (host threads sharing the call on CPU), or is empty (one launch:
    chunk k is kernel item k)."""

    counter: wp.array(dtype=wp.int32)
    chunk: int
    count: int


@wp.func
def claimed_items(claims: Claims, k: int) -> wp.vec2i:
    """The items [first, last) that kernel item k works on: empty once every chunk is
    taken."""
    c = k
    if claims.counter.shape[0] > 0:
        c = shared_add(claims.counter, 0, 1)
    if c > (claims.count - 1) / claims.chunk:  # none left (before c * chunk could overflow)
        return wp.vec2i(claims.count, claims.count)
    first = c * claims.chunk
    return wp.vec2i(first, wp.min(first + claims.chunk, claims.count))


def unclaimed(n: int, chunk: int, device) -> Claims:
    """Claims of one launch over n items (no counter): kernel item k works on chunk k."""
    claims = Claims()
    claims.counter = wp.empty(0, dtype=wp.int32, device=device)
    claims.chunk, claims.count = chunk, n
    return claims


def launch_claimed(kernel, n: int, args: list, device, threads: int, align: int = 1) -> None:
    """`kernel` over n items in chunks: its last parameter, a Claims, is set here, its
    others are `args`. On CPU each of the call's `threads` host threads runs one
    launch, every launch taking the next unclaimed chunk (at least MIN_CLAIM items, a
    multiple of `align`) until none is left: a thread that wakes late or meets costly items
    takes fewer, and no array is sliced. There a numpy array may stand for an array
    parameter (wrapped without a Warp array object, which costs ~7 us). On CUDA one launch,
    a kernel item per chunk of `align` items."""
    if n == 0:
        return
    if not device.is_cpu:
        wp.launch(kernel, dim=-(-n // align), inputs=[*args, unclaimed(n, align, device)],
                  device=device)
        return
    claims = Claims()
    claims.count = n
    threads = max(1, min(threads, -(-n // MIN_CLAIM)))
    # one thread: one chunk, one kernel item
    chunk = n if threads == 1 else max(MIN_CLAIM, -(-n // (threads * CLAIMS_PER_THREAD)))
    claims.chunk = -(-chunk // align) * align
    chunks = -(-n // claims.chunk)
    key = launch_key(kernel, device, args)
    idle = _idle_launches.setdefault(key, [])
    try:
        cmd, counter, next_chunk = idle.pop()
    except IndexError:  # none idle: record one (62 us for the trace kernel)
        counter = wp.zeros(1, dtype=wp.int32, device=device)
        next_chunk = counter.numpy()
        values = [wp.empty(0, dtype=a.type.dtype, device=device)
                  if isinstance(x, np.ndarray) else x
                  for x, a in zip(args, kernel.adj.args, strict=False)]
        cmd = wp.launch(kernel, dim=1, inputs=[*values, claims], device=device,
                        record_cmd=True)
        cmd.fwd_args = cmd.adj_args = None  # kept between calls: it must keep no array alive
    try:
        next_chunk[0] = 0
        claims.counter = counter
        for i, x in enumerate([*args, claims]):
            if isinstance(x, np.ndarray):
                _set_host_array(cmd, i, x)
            else:
                cmd.set_param_at_index(i, x)
        cmd.set_dim(chunks)

        def run(k: int) -> None:
            if k == 0 or next_chunk[0] < chunks:  # a late thread finds every chunk taken
                cmd.launch()  # concurrent launches of one Launch only read its parameters

        run_parts(run, threads, threads)
    finally:
        idle.append((cmd, counter, next_chunk))


# recorded launches of launch_claimed that no call is using, with their chunk counters (and
# a numpy view of each), per launch_key
_idle_launches: dict[tuple, list] = {}


def claimed_arg(a: np.ndarray, dtype, device) -> np.ndarray | wp.array:
    """An array argument of launch_claimed: on CPU the contiguous numpy array itself
    (launch_claimed wraps it), elsewhere a device copy."""
    return np.ascontiguousarray(a) if device.is_cpu else wp.array(a, dtype=dtype, device=device)


@functools.cache
def _array_rows(kernel, i: int) -> tuple[np.dtype, int]:
    """The numpy scalar type and the row bytes of 1-d array parameter i of `kernel`."""
    dtype = kernel.adj.args[i].type.dtype
    return (np.dtype(wp.dtype_to_numpy(getattr(dtype, "_wp_scalar_type_", dtype))),
            wp.types.type_size_in_bytes(dtype))


def _set_host_array(cmd, i: int, a: np.ndarray) -> None:
    """Parameter i of a recorded CPU launch set to a contiguous numpy array, in place in
    the launch's own `array_t` (Warp's ctypes array)."""
    scalar, row = _array_rows(cmd.kernel, i)
    if a.dtype != scalar or not a.flags.c_contiguous or a.size * a.itemsize != len(a) * row:
        raise TypeError(f"parameter {cmd.kernel.adj.args[i].label}: a contiguous "
                        f"{scalar.name} array of {row}-byte rows, got {a.dtype} {a.shape}")
    param = cmd.params[i + 1]
    param.data = a.ctypes.data
    param.shape[0] = len(a)
    param.strides[0] = row
