"""`scenesort serve --exit-with-stdin`: the service ends when the program that started it does.

The add-on starts the service with a pipe as its stdin and never writes to it. However
Blender ends (it quits, crashes or is killed), the operating system closes its end of the
pipe, on every OS, and the read here returns end-of-file. The service then stops as SIGTERM
stops it (cancelling its work), and exits outright if that takes longer than GRACE_S:
nobody is left to answer.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import threading
from typing import BinaryIO

GRACE_S = 1.0
log = logging.getLogger("scenesort.serve")


def _wait_for_eof(stream: BinaryIO) -> None:
    with contextlib.suppress(OSError, ValueError):
        while stream.read(4096):  # whatever arrives is ignored: only the end matters
            pass
    log.warning("the program that started the service went away (stdin closed): stopping")
    deadline = threading.Timer(GRACE_S, os._exit, args=(0,))
    deadline.daemon = True  # a stop that finishes in time exits at once, not at the deadline
    deadline.start()
    signal.raise_signal(signal.SIGTERM)  # uvicorn's handler, in the main thread


def exit_with_stdin(stream: BinaryIO | None = None) -> threading.Thread:
    """Start the daemon thread that stops this process when `stream` (stdin) closes."""
    thread = threading.Thread(
        target=_wait_for_eof,
        args=(stream or sys.stdin.buffer,),
        name="scenesort-lifeline",
        daemon=True,
    )
    thread.start()
    return thread
