"""Start and stop the local service (`scenesort serve`) as a child process of Blender.

By default the child is Blender's own Python (`sys.executable`) running the engine
that the extension zip installed into Blender's extensions site-packages; the
"Service command" preference overrides that for an install of your own. Each start
makes a fresh token (the service refuses requests without it) and hands it over in
the child's environment as $SCENESORT_TOKEN, never on its command line where `ps`
shows it; `token_for(url)` gives it to the client. The child never outlives Blender:
it is stopped on unregister and at interpreter exit (atexit); if Blender dies without
cleaning up, the child's stdin, a pipe only Blender holds, closes and
`serve --exit-with-stdin` stops (every OS); on Windows a kill-on-close Job Object also
ends it (winjob.py), and on Linux the kernel sends it SIGTERM (PR_SET_PDEATHSIG). Only
the process started here is stopped.
"""

from __future__ import annotations

import atexit
import concurrent.futures
import contextlib
import ctypes
import importlib.util
import ipaddress
import os
import re
import secrets
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import urllib.parse
from pathlib import Path

from . import winjob

STOP_TIMEOUT_S = 5.0
ENGINE_PACKAGE = "scenesort.backend"  # the service's package inside the scenesort wheel
ENGINE_COMMAND = f"{ENGINE_PACKAGE}.commands"  # `python -m` this: the `scenesort` command
_PR_SET_PDEATHSIG = 1
# `scenesort serve` prints this first, with the port it bound (also for --port 0).
_SERVING = re.compile(r"scenesort serving on (http://\S+)")

_process: subprocess.Popen | None = None
_log_path: Path | None = None
_token: str | None = None  # the started service's token, and the address it serves
_address: tuple[str, int] | None = None


class LaunchError(Exception):
    """The service could not be started; the message is meant for the user."""


def is_loopback(host: str) -> bool:
    """Whether `host` (a URL's host name) can only be this computer."""
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a name: it may resolve to anything


def host_port(url: str) -> tuple[str, int]:
    """Host and port of a service URL; only loopback URLs can be started locally."""
    parts = urllib.parse.urlsplit(url.strip())
    host = parts.hostname or ""
    if not is_loopback(host):
        raise LaunchError(
            f"Only a local service can be started from Blender; '{url}' is not on 127.0.0.1"
        )
    try:
        port = parts.port or 8765
    except ValueError:
        raise LaunchError(f"'{url}' has an invalid port") from None
    return ("127.0.0.1" if host.lower() == "localhost" else host), port


def split_command(command: str) -> list[str]:
    """A command line as its words: quotes group, backslashes stay as they are.

    POSIX `shlex.split` would read `C:\\Users\\me\\scenesort.exe` as escapes and drop
    every backslash; paths with spaces are quoted on every platform.
    """
    lexer = shlex.shlex(command, posix=True)
    lexer.whitespace_split = True
    lexer.escape = ""  # no escape character: a Windows path keeps its backslashes
    lexer.commenters = ""
    try:
        return list(lexer)
    except ValueError as exc:
        raise LaunchError(f"The service command '{command}' cannot be parsed: {exc}") from None


def engine_root() -> Path | None:
    """The folder that holds the bundled engine, `scenesort/` (Blender puts its extensions'
    site-packages first on `sys.path`), found without importing the engine: only the two
    package markers `scenesort` and `scenesort.backend`, which import nothing, run."""
    try:
        spec = importlib.util.find_spec(ENGINE_PACKAGE)
    except ImportError:  # no `scenesort` package at all
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    folder = Path(next(iter(spec.submodule_search_locations)))
    if not (folder / "commands" / "__main__.py").is_file():
        return None
    top = importlib.util.find_spec(ENGINE_PACKAGE.split(".")[0])
    return Path(top.origin).parent.parent if top and top.origin else None


def _bundled_engine() -> Path:
    root = engine_root()
    if root is None:
        raise LaunchError(
            "The scenesort engine is not installed beside the add-on: install the zip made "
            "by 'scenesort addon-zip --platform ...', or set 'Service command' in the "
            "add-on preferences to a scenesort program of your own"
        )
    return root


def command_line(command: str, host: str, port: int, device: str = "cpu") -> list[str]:
    """The child's argument list (no shell involved): `command` (the preference's
    override) if set, else Blender's own Python running the bundled engine, then
    `serve --host H --port P --exit-with-stdin --device D`."""
    serve = ["serve", "--host", host, "--port", str(port), "--exit-with-stdin",
             "--device", device]  # fmt: skip
    if not command.strip():
        _bundled_engine()
        # -s: the user's own site-packages must not shadow the bundled wheels.
        return [sys.executable, "-s", "-m", ENGINE_COMMAND, *serve]
    argv = split_command(command)
    if not argv:
        raise LaunchError("The service command is empty: set it in the add-on preferences")
    exe = shutil.which(argv[0])
    if exe is None:
        raise LaunchError(
            f"The program '{argv[0]}' was not found: install scenesort, or set the full "
            "path of its 'scenesort' command in the add-on preferences"
        )
    return [exe, *argv[1:], *serve]


def child_env(command: str, token: str | None) -> dict[str, str]:
    """The child's environment: Blender's, the service's token (unless None: the device
    probe), and for the bundled engine exactly the extension's site-packages as the path
    (Blender's own Python finds numpy itself)."""
    env = {**os.environ, **({} if token is None else {"SCENESORT_TOKEN": token})}
    if not command.strip():
        for name in ("PYTHONHOME", "PYTHONPATH", "PYTHONSTARTUP"):
            env.pop(name, None)
        env["PYTHONPATH"] = str(_bundled_engine())
    return env


def log_path() -> Path | None:
    """The log file of the service started last (stdout and stderr), if any."""
    return _log_path


def running() -> bool:
    """Whether the service started by this add-on is still alive."""
    return _process is not None and _process.poll() is None


def served_url() -> str | None:
    """The URL the running child listens on (from its first line), None before that."""
    if not running() or _log_path is None:
        return None
    with contextlib.suppress(OSError), _log_path.open(errors="replace") as log:
        for line in log:
            if match := _SERVING.search(line):
                return match.group(1)
    return None


def last_log_line() -> str:
    """The latest line the service wrote, e.g. while it starts; '' if none."""
    if _log_path is None or not _log_path.exists():
        return ""
    lines = _log_path.read_text(errors="replace").strip().splitlines()
    return lines[-1] if lines else ""


def exit_message() -> str:
    """Why the started process ended early: its exit code and the end of its log."""
    code = None if _process is None else _process.poll()
    tail = last_log_line()
    return f"the service exited (code {code})" + (f": {tail}" if tail else "")


def _load_prctl():  # noqa: ANN202 - a ctypes function or None
    # Looked up before any fork: loading libraries in the forked child could deadlock.
    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None


_prctl = _load_prctl()
# Linux sends the parent-death signal when the THREAD that forked the child ends, not the
# process: a render's or an operator's worker thread would take the service with it. So
# every child is forked by this one thread, which lives as long as Blender's Python.
_launcher = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="scenesort-launch")


def _die_with_parent(parent_pid: int) -> None:
    """In the child before exec: ask Linux to SIGTERM it when Blender goes away."""
    with contextlib.suppress(Exception):
        _prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    if os.getppid() != parent_pid:  # Blender already died between fork and prctl
        os._exit(1)


def token_for(url: str) -> str | None:
    """The token of the service this add-on started, if it serves `url`."""
    if not running():
        return None
    served = served_url()  # the bound port, also when it was started with port 0
    try:
        return _token if host_port(url) == (host_port(served) if served else _address) else None
    except LaunchError:
        return None


def start(command: str, url: str, device: str = "cpu") -> subprocess.Popen:
    """Launch the service for `url` (port 0: any free one) unless one of ours runs."""
    global _process, _log_path, _token, _address
    if running():
        return _process
    host, port = host_port(url)
    argv = command_line(command, host, port, device)
    token = secrets.token_urlsafe(32)
    env = child_env(command, token)
    # The bundled engine runs in its own folder: `-m` puts the working folder first on
    # the path, and Blender's (or a temporary) one may hold anything.
    cwd = None if command.strip() else str(_bundled_engine())
    _token, _address = token, (host, port)
    if _log_path is not None:  # the previous run's log; only the latest one is kept
        _log_path.unlink(missing_ok=True)
    fd, name = tempfile.mkstemp(prefix="scenesort-service-", suffix=".log")
    _log_path = Path(name)
    parent = os.getpid()
    preexec = (lambda: _die_with_parent(parent)) if _prctl is not None else None
    try:
        with os.fdopen(fd, "wb") as log:
            _process = _launcher.submit(
                subprocess.Popen,
                argv,
                stdin=subprocess.PIPE,  # never written: it closes when Blender ends
                stdout=log,
                stderr=subprocess.STDOUT,
                env=env,
                cwd=cwd,
                preexec_fn=preexec,  # only prctl: it must run in the child before exec
                close_fds=True,
                creationflags=winjob.CREATE_NO_WINDOW if sys.platform == "win32" else 0,
            ).result()
    except OSError as exc:
        raise LaunchError(f"Could not run {argv[0]}: {exc.strerror or exc}") from None
    winjob.kill_with_blender(_process)
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
    if proc.stdin is not None:
        proc.stdin.close()
    return True


atexit.register(stop)
