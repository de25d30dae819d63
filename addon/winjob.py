"""Windows: a Job Object that ends the service when Blender's process ends.

Blender holds the job's only handle; Windows closes it when Blender exits or is killed,
and KILL_ON_JOB_CLOSE then ends every process in the job. This is the Windows half of
"the service never outlives Blender" (the stdin pipe that `scenesort serve
--exit-with-stdin` watches is the portable half). Elsewhere `kill_with_blender` does
nothing. Written against the Win32 documentation; not run on Windows by the tests.
"""

from __future__ import annotations

import ctypes
import subprocess
import sys

_JOB_OBJECT_EXTENDED_LIMIT_INFORMATION_CLASS = 9  # JobObjectExtendedLimitInformation
_JOB_OBJECT_LIMIT_KILL_ON_JOB_CLOSE = 0x2000
# No console window for the child (Blender on Windows is a GUI program).
CREATE_NO_WINDOW = getattr(subprocess, "CREATE_NO_WINDOW", 0x08000000)

_job = None  # the job's handle, kept open for as long as Blender runs


class _IoCounters(ctypes.Structure):
    _fields_ = [(name, ctypes.c_ulonglong) for name in (
        "ReadOperationCount", "WriteOperationCount", "OtherOperationCount",
        "ReadTransferCount", "WriteTransferCount", "OtherTransferCount")]  # fmt: skip


class _BasicLimits(ctypes.Structure):
    _fields_ = [
        ("PerProcessUserTimeLimit", ctypes.c_longlong),
        ("PerJobUserTimeLimit", ctypes.c_longlong),
        ("LimitFlags", ctypes.c_uint32),
        ("MinimumWorkingSetSize", ctypes.c_size_t),
        ("MaximumWorkingSetSize", ctypes.c_size_t),
        ("ActiveProcessLimit", ctypes.c_uint32),
        ("Affinity", ctypes.c_size_t),
        ("PriorityClass", ctypes.c_uint32),
        ("SchedulingClass", ctypes.c_uint32),
    ]


class _ExtendedLimits(ctypes.Structure):
    _fields_ = [
        ("BasicLimitInformation", _BasicLimits),
        ("IoInfo", _IoCounters),
        ("ProcessMemoryLimit", ctypes.c_size_t),
        ("JobMemoryLimit", ctypes.c_size_t),
        ("PeakProcessMemoryUsed", ctypes.c_size_t),
        ("PeakJobMemoryUsed", ctypes.c_size_t),
    ]


def _kill_on_close_job():  # noqa: ANN202 - a Windows HANDLE (int)
    kernel32 = ctypes.WinDLL("kernel32", use_last_error=True)
    kernel32.CreateJobObjectW.restype = ctypes.c_void_p
    job = kernel32.CreateJobObjectW(None, None)
    if not job:
        raise ctypes.WinError(ctypes.get_last_error())
    limits = _ExtendedLimits()
    limits.BasicLimitInformation.LimitFlags = _JOB_OBJECT_LIMIT_KILL_ON_JOB_CLOSE
    ok = kernel32.SetInformationJobObject(
        ctypes.c_void_p(job), _JOB_OBJECT_EXTENDED_LIMIT_INFORMATION_CLASS,
        ctypes.byref(limits), ctypes.sizeof(limits),
    )  # fmt: skip
    if not ok:
        raise ctypes.WinError(ctypes.get_last_error())
    return job


def kill_with_blender(proc: subprocess.Popen) -> bool:
    """Put `proc` into Blender's kill-on-close job (Windows); False where that is not done
    (another OS, or Windows refused: the stdin pipe still ends the service)."""
    global _job
    if sys.platform != "win32":
        return False
    try:
        if _job is None:
            _job = _kill_on_close_job()
        kernel32 = ctypes.WinDLL("kernel32", use_last_error=True)
        handle = ctypes.c_void_p(int(proc._handle))  # Popen's process handle on Windows
        return bool(kernel32.AssignProcessToJobObject(ctypes.c_void_p(_job), handle))
    except OSError:
        return False
