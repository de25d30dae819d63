"""Host helper threads that wait for a call's work in native code, spinning, as TBB's
workers wait for Embree's: a CPU launch shared between host threads (core.claim) hands a
helper the kernel's entry point and its packed arguments through a control row, and the
helper, already running native code outside Python's lock, starts it within a
microsecond. Through Python (a pool thread woken by a future) a helper started 15 us
after it was told (median, 29 us at the 90th percentile on a 2-vCPU VM) and the caller
waited ~25 us more at the end: a third of a 10k-ray call's work (docs/benchmarks.md,
"Small calls").

A helper spins for SPIN_SECONDS after its last job, then goes back to Python and sleeps
on an event until a caller wakes it; a call that finds it asleep wakes it and shares the
work the same way. The control row's state changes by compare-and-swap where a helper
and a caller may race (a caller posting a job, a helper going to sleep); the caller
that owns a helper (its lock) is the only one that posts to it.

CPU only: the entry points are Warp's CPU kernels (`launch_bounds_t*`, args struct*), the
waiting uses the time-stamp counter; on CUDA the functions compile to nothing.
"""

from __future__ import annotations

import atexit
import ctypes
import os
import threading
import time

import warp as wp

from .compile_options import MODULE_OPTIONS
from .launch import cpu_cores

wp.set_module_options(MODULE_OPTIONS)

SPIN_SECONDS = 0.0005  # how long an idle helper spins before it sleeps
WAIT_SECONDS = 0.0002  # how long a caller spins for its helpers before it sleeps between looks

# A control row's state (word 0): a helper spinning, a job posted, a job running, a helper
# asleep in Python; words 1-3: the job's entry point, bounds and arguments; word 4: stop.
SPINNING, JOB, RUNNING, ASLEEP = 0, 1, 2, 3
STOP_WORD = 4
ROW = 16  # int64 words per helper: 128 bytes, two cache lines of its own

_ROW = f"""
    constexpr long long SPINNING = {SPINNING}, JOB = {JOB}, RUNNING = {RUNNING}, ASLEEP = {ASLEEP};
    constexpr int STOP_WORD = {STOP_WORD};
    long long* c = (long long*)ctl.data + row * {ROW};
"""

_SERVE = """
#if defined(__CUDA_ARCH__)
    return 0;
#else""" + _ROW + """
    typedef void (*Entry)(void*, void*);
    unsigned long long since = __builtin_ia32_rdtsc();
    for (;;) {
        long long s = __atomic_load_n(&c[0], __ATOMIC_ACQUIRE);
        if (__atomic_load_n(&c[STOP_WORD], __ATOMIC_ACQUIRE))
            return ASLEEP;
        if (s == JOB) {
            if (__atomic_compare_exchange_n(&c[0], &s, RUNNING, false, __ATOMIC_ACQ_REL,
                                            __ATOMIC_ACQUIRE)) {
                ((Entry)c[1])((void*)c[2], (void*)c[3]);
                __atomic_store_n(&c[0], SPINNING, __ATOMIC_RELEASE);
                since = __builtin_ia32_rdtsc();
            }
        } else if (s == ASLEEP) {
            return ASLEEP;
        } else if ((long long)(__builtin_ia32_rdtsc() - since) > cycles) {
            if (__atomic_compare_exchange_n(&c[0], &s, ASLEEP, false, __ATOMIC_ACQ_REL,
                                            __ATOMIC_ACQUIRE))
                return ASLEEP;
        } else {
            __builtin_ia32_pause();
        }
    }
#endif
"""

_POST = """
#if defined(__CUDA_ARCH__)
    return 0;
#else""" + _ROW + """
    long long s = SPINNING;
    __atomic_compare_exchange_n(&c[0], &s, JOB, false, __ATOMIC_ACQ_REL, __ATOMIC_ACQUIRE);
    return (int)s;
#endif
"""

_WAIT = """
#if defined(__CUDA_ARCH__)
    return 0;
#else""" + _ROW + """
    long long s = JOB;
    if (__atomic_compare_exchange_n(&c[0], &s, SPINNING, false, __ATOMIC_ACQ_REL,
                                    __ATOMIC_ACQUIRE))
        return SPINNING;
    const unsigned long long since = __builtin_ia32_rdtsc();
    while ((s = __atomic_load_n(&c[0], __ATOMIC_ACQUIRE)) == RUNNING
           && (long long)(__builtin_ia32_rdtsc() - since) < cycles)
        __builtin_ia32_pause();
    return (int)s;
#endif
"""

_CLOCK = """
#if defined(__CUDA_ARCH__)
    return 0;
#else
    return (long long)__builtin_ia32_rdtsc();
#endif
"""


@wp.func_native(_SERVE)
def serve(ctl: wp.array(dtype=wp.int64), row: int, cycles: wp.int64) -> int:
    """Runs the jobs posted to control row `row` (each taken by moving JOB to RUNNING)
    until it has been idle `cycles` time-stamp counts or is told to stop; ASLEEP."""
    ...


@wp.func_native(_POST)
def post(ctl: wp.array(dtype=wp.int64), row: int) -> int:
    """Posts the job in row `row` to a spinning helper; the state found (SPINNING: posted)."""
    ...


@wp.func_native(_WAIT)
def wait(ctl: wp.array(dtype=wp.int64), row: int, cycles: wp.int64) -> int:
    """Takes back the job in row `row` if no helper took it yet (a sleeping helper not yet
    awake: the caller did the work), else spins while it runs, for at most `cycles`
    counts; the state seen last (RUNNING: still running)."""
    ...


@wp.func_native(_CLOCK)
def clock() -> wp.int64:
    ...


@wp.kernel
def serve_kernel(ctl: wp.array(dtype=wp.int64), row: int, cycles: wp.int64):
    serve(ctl, row, cycles)  # its answer unread: the helper's loop reads the stop word


@wp.kernel
def post_kernel(ctl: wp.array(dtype=wp.int64), row: int, out: wp.array(dtype=int)):
    out[row] = post(ctl, row)


@wp.kernel
def wait_kernel(ctl: wp.array(dtype=wp.int64), row: int, cycles: wp.int64,
                out: wp.array(dtype=int)):
    out[row] = wait(ctl, row, cycles)


@wp.kernel
def clock_kernel(out: wp.array(dtype=wp.int64)):
    out[0] = clock()


_ENTRY = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_void_p)


class Entry:
    """A CPU kernel's entry point called directly with packed arguments (what Warp's
    `invoke` does after packing a new struct from a recorded launch's parameters): the
    struct is kept, so a call sets only what changed in it. Warp 1.19's CPU entry,
    `name_cpu_forward(launch_bounds_t*, args*)` (the version pyproject.toml pins)."""

    __slots__ = ("fn", "address", "code", "bounds", "args", "fields", "bounds_address",
                 "args_address")

    def __init__(self, cmd) -> None:
        if cmd.block_dim > 1:
            raise ValueError(f"{cmd.kernel.key}: a cooperative (tiled) kernel launches "
                             "through Warp, which checks its blocks' errors")
        # The loaded module the entry point lies in, kept: Warp unloads a module's code when
        # nothing holds its executable (as a load of the same module on another thread
        # replaced it: a service's warm-up beside its first job), and a call into it then
        # jumped to unmapped memory.
        self.code = cmd.module_exec
        hooks = cmd.hooks
        self.address = ctypes.cast(hooks.forward, ctypes.c_void_p).value
        self.fn = _ENTRY(self.address)
        self.fields = [(a.label, type(p)) for a, p in zip(cmd.kernel.adj.args, cmd.params[1:],
                                                          strict=False)]
        struct = type("ArgsStruct", (ctypes.Structure,), {"_fields_": self.fields})
        self.args = struct()
        for (name, _), p in zip(self.fields, cmd.params[1:], strict=False):
            setattr(self.args, name, p)
        self.args_address = ctypes.addressof(self.args)
        self.set_bounds(cmd.params[0])

    def set_bounds(self, bounds) -> None:
        self.bounds = bounds
        self.bounds_address = ctypes.addressof(bounds)

    def __call__(self) -> None:
        self.fn(self.bounds_address, self.args_address)


def _entry_of(kernel, inputs: list) -> Entry:
    cmd = wp.launch(kernel, dim=1, inputs=inputs, device="cpu", record_cmd=True)
    return Entry(cmd)


class _Helpers:
    """The process's helper threads (cores - 1), their control rows and their entries."""

    def __init__(self, count: int, spin_seconds: float = SPIN_SECONDS) -> None:
        self.count = count
        self.ctl = wp.zeros(count * ROW, dtype=wp.int64, device="cpu")
        self.state = self.ctl.numpy()
        self.out = wp.zeros(count, dtype=int, device="cpu")  # what post and wait found
        self.found = self.out.numpy()
        rate = _tsc_rate()
        self.owners = [threading.Lock() for _ in range(count)]
        self.wakes = [threading.Event() for _ in range(count)]
        self.serves = [_entry_of(serve_kernel, [self.ctl, r, int(spin_seconds * rate)])
                       for r in range(count)]
        self.posts = [_entry_of(post_kernel, [self.ctl, r, self.out]) for r in range(count)]
        self.waits = [_entry_of(wait_kernel, [self.ctl, r, int(WAIT_SECONDS * rate),
                                              self.out]) for r in range(count)]
        for r in range(count):
            self.state[r * ROW] = ASLEEP
        self.threads = [threading.Thread(target=self._main, args=(r,), daemon=True,
                                         name=f"kernels-helper-{r}") for r in range(count)]
        for t in self.threads:
            t.start()

    def _main(self, r: int) -> None:
        while not self.state[r * ROW + STOP_WORD]:
            self.wakes[r].wait()
            self.wakes[r].clear()
            self.serves[r]()

    def take(self, wanted: int) -> list[int] | None:
        """`wanted` helpers no other call is using, now owned by the caller; None (and
        none taken) where there are not that many."""
        taken = []
        for r, owner in enumerate(self.owners):
            if len(taken) == wanted:
                break
            if owner.acquire(blocking=False):
                taken.append(r)
        if len(taken) == wanted:
            return taken
        self.give_back(taken)
        return None

    def give_back(self, taken: list[int]) -> None:
        for r in taken:
            self.owners[r].release()

    def run(self, entry: Entry, helpers: list[int]) -> None:
        """entry() on the caller and on each of `helpers` (taken, then given back) that
        takes the job before the caller is done with it; returns once every run ended."""
        state = self.state
        try:
            for r in helpers:
                c = r * ROW
                state[c + 1:c + 4] = entry.address, entry.bounds_address, entry.args_address
                self.posts[r]()
                if self.found[r] == ASLEEP:  # asleep in Python: only a caller moves it on
                    state[c] = JOB
                    self.wakes[r].set()
            entry()
        finally:
            for r in helpers:
                self.waits[r]()
                while self.found[r] == RUNNING:
                    time.sleep(5e-5)
                    self.waits[r]()
            self.give_back(helpers)

    def stop(self) -> None:
        """Stops every helper (at exit: Warp's code must not be left running)."""
        for r in range(self.count):
            self.state[r * ROW + STOP_WORD] = 1
            self.wakes[r].set()
        for t in self.threads:
            t.join(timeout=1.0)


def _tsc_rate() -> float:
    """Time-stamp counts per second (a 10 ms measurement)."""
    out = wp.zeros(1, dtype=wp.int64, device="cpu")
    read = _entry_of(clock_kernel, [out])
    ticks = out.numpy()
    read()
    t0, c0 = time.perf_counter(), int(ticks[0])
    time.sleep(0.01)
    read()
    return (int(ticks[0]) - c0) / (time.perf_counter() - t0)


_helpers: _Helpers | None = None
_lock = threading.Lock()


def helpers() -> _Helpers | None:
    """The process's helpers (made on first use); None on one core or off x86-64."""
    global _helpers
    if _helpers is None and cpu_cores() > 1 and _x86_64():
        with _lock:
            if _helpers is None:
                _helpers = _Helpers(cpu_cores() - 1)
                atexit.register(_helpers.stop)
    return _helpers


def _x86_64() -> bool:
    return os.uname().machine in ("x86_64", "AMD64")


def _forget() -> None:  # a forked child has the parent's helpers' rows, not their threads
    global _helpers
    _helpers = None


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget)
