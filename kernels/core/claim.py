"""Chunks of one call's items, claimed by the host threads that share it
(`launch_claimed`): each thread's launch takes the next unclaimed chunk from a counter
until none is left, the pool's work claiming (2012 paper, sec. 3.3) at the scale of one
kernel call. A kernel item is a chunk of items, not one: Warp's CPU launch loop costs
about 12 ns a kernel item (measured: 10^6 cheap any-hit rays ran at 24.5 Mrays/s one ray a
kernel item, 35 Mrays/s 64 rays and more a kernel item).
"""

from __future__ import annotations

import ctypes

import numpy as np
import warp as wp

from .atomics import shared_add
from .compile_options import MODULE_OPTIONS
from .helpers import Entry, helpers
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
    others are `args`. On CPU each of the call's `threads` host threads (the caller and
    helpers that wait natively: core.helpers) runs the kernel's entry once, each run taking
    the next unclaimed chunk (at least MIN_CLAIM items, a multiple of `align`) until none
    is left: a thread that starts late or meets costly items takes fewer, and no array is
    sliced. There a numpy array may stand for an array parameter (wrapped without a Warp
    array object, which costs ~7 us). On CUDA one launch, a kernel item per chunk of
    `align` items."""
    if n == 0:
        return
    if not device.is_cpu:
        wp.launch(kernel, dim=-(-n // align), inputs=[*args, unclaimed(n, align, device)],
                  device=device)
        return
    threads = max(1, min(threads, -(-n // MIN_CLAIM)))
    # one thread: one chunk, one kernel item
    chunk = n if threads == 1 else max(MIN_CLAIM, -(-n // (threads * CLAIMS_PER_THREAD)))
    chunk = -(-chunk // align) * align
    chunks = -(-n // chunk)
    key = launch_key(kernel, device, args)
    idle = _idle_launches.setdefault(key, [])
    launch = idle.pop() if idle else _Recorded(kernel, args, device)
    try:
        launch.next_chunk[0] = 0
        launch.claims.chunk, launch.claims.count = chunk, n  # in place: no struct packed
        launch.set(args, chunks)
        entry, next_chunk = launch.entry, launch.next_chunk
        pool = helpers() if threads > 1 else None
        taken = pool.take(threads - 1) if pool is not None else None
        if threads == 1:
            entry()
        elif taken is not None:
            pool.run(entry, taken)
        else:  # the helpers busy with another call, or more threads than cores

            def run(k: int) -> None:
                if k == 0 or next_chunk[0] < chunks:  # a late thread finds every chunk taken
                    entry()  # concurrent calls of one entry only read its arguments

            run_parts(run, threads, threads)
    finally:
        idle.append(launch)


class _Recorded:
    """A recorded launch of launch_claimed's kernel, its entry (its arguments packed once,
    kept), its chunk counter (and a numpy view of it) and the numbers it was last given: a
    call sets only what changed (a small call's fixed cost is mostly setting parameters,
    ~1.5 us each through Warp)."""

    __slots__ = ("cmd", "entry", "counter", "next_chunk", "claims", "host", "other", "last",
                 "dim")

    def __init__(self, kernel, args: list, device) -> None:
        # recording costs 62 us for the trace kernel, so recorded launches are kept
        self.counter = wp.zeros(1, dtype=wp.int32, device=device)
        self.next_chunk = self.counter.numpy()
        claims = Claims()
        claims.counter, claims.chunk, claims.count = self.counter, 1, 0
        values = [wp.empty(0, dtype=a.type.dtype, device=device)
                  if isinstance(x, np.ndarray) else x
                  for x, a in zip(args, kernel.adj.args, strict=False)]
        self.cmd = wp.launch(kernel, dim=1, inputs=[*values, claims], device=device,
                             record_cmd=True)
        self.cmd.fwd_args = self.cmd.adj_args = None  # kept between calls: no array kept alive
        self.entry = Entry(self.cmd)
        packed = self.entry.args
        self.claims = getattr(packed, kernel.adj.args[len(args)].label)  # set in place
        # the numpy arrays' parameters (launch_key fixes which arguments are arrays):
        # index, Warp's array_t in the packed arguments, numpy scalar type, row bytes
        self.host = [(i, getattr(packed, kernel.adj.args[i].label),
                      *_array_rows(kernel.adj.args[i].type.dtype))
                     for i, x in enumerate(args) if isinstance(x, np.ndarray)]
        for _, param, _, row in self.host:
            param.strides[0] = row
        self.other = [i for i, x in enumerate(args) if not isinstance(x, np.ndarray)]
        self.last: list = [None] * len(args)
        self.dim = 1

    def set(self, args: list, dim: int) -> None:
        for i, param, scalar, row in self.host:
            a = args[i]  # set in place in the launch's array_t, no Warp array made
            if a.dtype != scalar or not a.flags.c_contiguous or a.nbytes != len(a) * row:
                raise TypeError(f"parameter {self.cmd.kernel.adj.args[i].label}: a contiguous "
                                f"{scalar.name} array of {row}-byte rows, got {a.dtype} "
                                f"{a.shape}")
            param.data = _address(a)
            param.shape[0] = len(a)
        for i in self.other:
            x = args[i]
            if type(x) not in (int, float):  # a struct is packed every call: mutable
                self._set_param(i, x)
            elif type(self.last[i]) is not type(x) or self.last[i] != x:
                self._set_param(i, x)
                self.last[i] = x
        if dim != self.dim:
            self.cmd.set_dim(dim)
            self.entry.set_bounds(self.cmd.params[0])
            self.dim = dim

    def _set_param(self, i: int, x) -> None:
        self.cmd.set_param_at_index(i, x)  # Warp packs it
        setattr(self.entry.args, self.entry.fields[i][0], self.cmd.params[i + 1])


# recorded launches of launch_claimed that no call is using, per launch_key
_idle_launches: dict[tuple, list[_Recorded]] = {}


def claimed_arg(a: np.ndarray, dtype, device) -> np.ndarray | wp.array:
    """An array argument of launch_claimed: on CPU the contiguous numpy array itself
    (launch_claimed wraps it), elsewhere a device copy."""
    return np.ascontiguousarray(a) if device.is_cpu else wp.array(a, dtype=dtype, device=device)


def _address(a: np.ndarray) -> int:
    """The address of a contiguous array's data: through ctypes' buffer view in 0.3 us,
    numpy's `a.ctypes.data` (1 us) for a read-only or empty array, which have none."""
    try:
        return ctypes.addressof(ctypes.c_char.from_buffer(a))
    except (TypeError, ValueError):
        return a.ctypes.data


def _array_rows(dtype) -> tuple[np.dtype, int]:
    """The numpy scalar type and the row bytes of a 1-d Warp array of `dtype`."""
    return (np.dtype(wp.dtype_to_numpy(getattr(dtype, "_wp_scalar_type_", dtype))),
            wp.types.type_size_in_bytes(dtype))
