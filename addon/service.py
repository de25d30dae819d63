"""Start and stop the local service (`scenesort serve`) as a child process of Blender.

Each start makes a fresh token (the service refuses requests without it) and hands it
over in the child's environment as $SCENESORT_TOKEN, never on its command line where
`ps` shows it; `token_for(url)` gives it to the client. The child never outlives
Blender: it is stopped on unregister and at interpreter exit (atexit), and on Linux the
kernel also sends it SIGTERM if Blender dies without cleaning up (PR_SET_PDEATHSIG).
Only the process started here is stopped.
"""

from __future__ import annotations

import atexit
import contextlib
import ctypes
import os
import secrets
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import urllib.parse
from pathlib import Path

STOP_TIMEOUT_S = 5.0
_PR_SET_PDEATHSIG = 1

_process: subprocess.Popen | None = None
_log_path: Path | None = None
_token: str | None = None  # the started service's token, and the address it serves
_address: tuple[str, int] | None = None


class LaunchError(Exception):
    """The service could not be started; the message is meant for the user."""


def host_port(url: str) -> tuple[str, int]:
    """Host and port of a service URL; only loopback URLs can be started locally."""
    parts = urllib.parse.urlsplit(url.strip())
    host = parts.hostname or ""
    if host not in {"127.0.0.1", "localhost", "::1"}:
        raise LaunchError(
            f"Only a local service can be started from Blender; '{url}' is not on 127.0.0.1"
        )
    try:
        port = parts.port or 8765
    except ValueError:
        raise LaunchError(f"'{url}' has an invalid port") from None
    return ("127.0.0.1" if host == "localhost" else host), port


def _load_prctl():  # noqa: ANN202 - a ctypes function or None
    # Looked up before any fork: loading libraries in the forked child could deadlock.
    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None


_prctl = _load_prctl()


def _die_with_parent(parent_pid: int) -> None:
    """In the child before exec: ask Linux to SIGTERM it when Blender goes away."""
    with contextlib.suppress(Exception):
        _prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    if os.getppid() != parent_pid:  # Blender already died between fork and prctl
        os._exit(1)


def command_line(command: str, host: str, port: int) -> list[str]:
    """`<command> serve --host H --port P` as an argument list (no shell involved)."""
    try:
        argv = shlex.split(command)
    except ValueError as exc:
        raise LaunchError(f"The service command '{command}' cannot be parsed: {exc}") from None
    if not argv:
        raise LaunchError("The service command is empty: set it in the add-on preferences")
    exe = shutil.which(argv[0])
    if exe is None:
        raise LaunchError(
            f"The program '{argv[0]}' was not found: install scenesort, or set the full "
            "path of its 'scenesort' command in the add-on preferences"
        )
    return [exe, *argv[1:], "serve", "--host", host, "--port", str(port)]


def token_for(url: str) -> str | None:
    """The token of the service this add-on started, if it serves `url`."""
    try:
        return _token if running() and host_port(url) == _address else None
    except LaunchError:
        return None


def log_path() -> Path | None:
    """The log file of the service started last (stdout and stderr), if any."""
    return _log_path


def running() -> bool:
    """Whether the service started by this add-on is still alive."""
    return _process is not None and _process.poll() is None


def exit_message() -> str:
    """Why the started process ended early: its exit code and the end of its log."""
    code = None if _process is None else _process.poll()
    tail = ""
    if _log_path is not None and _log_path.exists():
        lines = _log_path.read_text(errors="replace").strip().splitlines()
        tail = lines[-1] if lines else ""
    return f"the service exited (code {code})" + (f": {tail}" if tail else "")


def start(command: str, url: str) -> subprocess.Popen:
    """Launch the service for `url` unless this add-on already runs one."""
    global _process, _log_path, _token, _address
    if running():
        return _process
    host, port = host_port(url)
    _token, _address = secrets.token_urlsafe(32), (host, port)
    argv = command_line(command, host, port)
    if _log_path is not None:  # the previous run's log; only the latest one is kept
        _log_path.unlink(missing_ok=True)
    fd, name = tempfile.mkstemp(prefix="scenesort-service-", suffix=".log")
    _log_path = Path(name)
    parent = os.getpid()
    preexec = (lambda: _die_with_parent(parent)) if _prctl is not None else None
    try:
        with os.fdopen(fd, "wb") as log:
            _process = subprocess.Popen(
                argv,
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                env={**os.environ, "SCENESORT_TOKEN": _token},
                preexec_fn=preexec,  # only prctl: it must run in the child before exec
                close_fds=True,
            )
    except OSError as exc:
        raise LaunchError(f"Could not run {argv[0]}: {exc.strerror or exc}") from None
    return _process


def stop() -> bool:
    """Stop the service this add-on started (SIGTERM, then SIGKILL); True if one ran."""
    global _process
    proc, _process = _process, None
    if proc is None:
        return False
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(STOP_TIMEOUT_S)
    return True


atexit.register(stop)
