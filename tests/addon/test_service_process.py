"""The child service never outlives Blender: stop(), normal exit, and a crash."""

from __future__ import annotations

import os
import re
import shlex
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from blender_scenes import REPO

from addon import client, service
from tests.waiting import until

# Stands in for `scenesort serve`: sleeps (bounded) whatever arguments it gets.
SLEEPER = shlex.join([sys.executable, "-c", "import time; time.sleep(60)"])


def _alive(pid: int) -> bool:
    """Whether `pid` runs (a zombie counts as gone)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(") ")[-1][0] != "Z"
    except FileNotFoundError:
        return False


def _signalled(pid: int) -> bool:
    """Whether SIGTERM or SIGKILL is pending for `pid`: sent, not yet acted on."""
    status = Path(f"/proc/{pid}/status").read_text()
    pending = 0
    for line in status.splitlines():
        if line.startswith(("SigPnd:", "ShdPnd:")):
            pending |= int(line.split()[1], 16)
    return bool(pending & ((1 << (signal.SIGTERM - 1)) | (1 << (signal.SIGKILL - 1))))


def test_command_line_appends_serve_and_address() -> None:
    argv = service.command_line(SLEEPER, "127.0.0.1", 9999, "cuda:0")
    assert argv[0] == sys.executable
    assert argv[-8:] == ["serve", "--host", "127.0.0.1", "--port", "9999", "--exit-with-stdin",
                         "--device", "cuda:0"]  # fmt: skip
    with pytest.raises(service.LaunchError, match="was not found"):
        service.command_line("no-such-program-scenesort", "127.0.0.1", 1)
    assert service.host_port("http://localhost:1234/") == ("127.0.0.1", 1234)
    assert service.host_port("http://127.0.0.1") == ("127.0.0.1", 8765)


def test_stop_ends_the_child() -> None:
    proc = service.start(SLEEPER, "http://127.0.0.1:1")
    try:
        assert service.running() and _alive(proc.pid)
        assert service.start(SLEEPER, "http://127.0.0.1:1") is proc  # no second child
    finally:
        assert service.stop()
    assert proc.poll() is not None and not service.running()
    assert not service.stop()  # nothing left to stop


def test_a_child_started_from_a_finished_thread_lives_on() -> None:
    """Renders and operators start the service from worker threads, which end; Linux's
    parent-death signal follows the forking thread, so the child must not die with it."""
    started: list[subprocess.Popen] = []
    tids: list[int] = []

    def launch() -> None:
        tids.append(threading.get_native_id())
        started.append(service.start(SLEEPER, "http://127.0.0.1:1"))

    thread = threading.Thread(target=launch)
    thread.start()
    thread.join()
    try:
        # Linux sends the signal as the thread exits, before its task leaves /proc: once
        # it has, a signal due was sent, and is either pending or has ended the child.
        until(lambda: not Path(f"/proc/self/task/{tids[0]}").exists(),
              "the finished thread to leave /proc", 10.0)
        assert started and _alive(started[0].pid) and not _signalled(started[0].pid)
        assert service.running()
    finally:
        assert service.stop()


def test_each_start_hands_a_fresh_token_over_in_the_environment() -> None:
    """The token is in the child's environment and never in its argv (which `ps` shows);
    the client sends it only to the address the child serves."""
    tokens = []
    for _ in range(2):
        proc = service.start(SLEEPER, "http://127.0.0.1:1")
        try:
            token = service.token_for("http://localhost:1/")
            environ = Path(f"/proc/{proc.pid}/environ").read_bytes().split(b"\0")
            cmdline = Path(f"/proc/{proc.pid}/cmdline").read_bytes()
            assert token and f"SCENESORT_TOKEN={token}".encode() in environ
            assert token.encode() not in cmdline
            assert client.Client("http://127.0.0.1:1").token == token
            assert client.Client("http://127.0.0.1:2").token is None  # another service
            tokens.append(token)
        finally:
            service.stop()
    assert tokens[0] != tokens[1] and service.token_for("http://127.0.0.1:1") is None


@pytest.mark.parametrize("ending", ["normal_exit", "killed"])
def test_child_dies_with_its_parent(ending: str) -> None:
    """A Blender that exits (atexit) or is killed (no cleanup at all) takes the child along."""
    exit_code = "sys.exit(0)" if ending == "normal_exit" else "os.kill(os.getpid(), 9)"
    code = (
        "import os, sys; from addon import service;"
        f"p = service.start({SLEEPER!r}, 'http://127.0.0.1:1');"
        f"print(p.pid, flush=True); {exit_code}"
    )
    parent = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60
    )
    child = int(parent.stdout.split()[0])
    try:
        until(lambda: not _alive(child), f"service child {child} to end with its parent "
              f"({ending})", 10.0)
    finally:
        if _alive(child):
            os.kill(child, 9)


def test_a_killed_blender_takes_its_service_along_by_the_pipe_alone() -> None:
    """SIGKILL a headless Blender (bpy in a child Python) that started the real service, with
    Linux's parent-death signal switched off: the service's stdin, a pipe only Blender held,
    closes and the service is gone within 2 s. This is how it ends on macOS and Windows."""
    code = (
        "import os, sys, time\n"
        "import bpy\n"
        "sys.path.insert(0, sys.argv[1])\n"
        "from addon import service\n"
        "service._prctl = None  # no PR_SET_PDEATHSIG: only the pipe can end the child\n"
        "proc = service.start('', 'http://127.0.0.1:0')\n"
        "deadline = time.monotonic() + 300\n"
        "while service.served_url() is None and time.monotonic() < deadline:\n"
        "    assert proc.poll() is None, service.exit_message()\n"
        "    time.sleep(0.05)\n"
        "print(proc.pid, service.log_path(), service.served_url(), flush=True)\n"
        "os.kill(os.getpid(), 9)\n"
    )
    parent = subprocess.run([sys.executable, "-c", code, str(REPO)], cwd=REPO,
                            capture_output=True, text=True, timeout=360)  # fmt: skip
    assert parent.returncode == -signal.SIGKILL, parent.stderr[-3000:]
    pid, log, url = parent.stdout.split()
    try:
        assert url.startswith("http://127.0.0.1:")  # it was serving when Blender died
        until(lambda: not _alive(int(pid)), f"service {pid} to end after its Blender", 2.0)
        assert "stdin closed" in Path(log).read_text()  # the pipe ended it, not a signal
    finally:
        if _alive(int(pid)):
            os.kill(int(pid), 9)
        Path(log).unlink(missing_ok=True)


@pytest.mark.parametrize(
    ("command", "words"),
    [
        (r"C:\Users\me\venv\Scripts\scenesort.exe", [r"C:\Users\me\venv\Scripts\scenesort.exe"]),
        (
            r'"C:\Program Files\scenesort\scenesort.exe" --log-level debug',
            [r"C:\Program Files\scenesort\scenesort.exe", "--log-level", "debug"],
        ),
        ("'/opt/my tools/scenesort'", ["/opt/my tools/scenesort"]),
        ("/usr/bin/env scenesort", ["/usr/bin/env", "scenesort"]),
    ],
)
def test_split_keeps_backslashes_and_quoted_spaces(command: str, words: list[str]) -> None:
    assert service.split_command(command) == words


def test_a_missing_windows_program_is_named_in_full() -> None:
    path = r"C:\Users\me\venv\Scripts\scenesort.exe"
    with pytest.raises(service.LaunchError, match=re.escape(f"'{path}' was not found")):
        service.command_line(path, "127.0.0.1", 1)
    with pytest.raises(service.LaunchError, match="cannot be parsed"):
        service.command_line('"unclosed', "127.0.0.1", 1)


def test_default_launch_is_this_python_running_the_engine_on_its_path() -> None:
    """No command: Blender's own interpreter, the engine's folder as the whole path."""
    argv = service.command_line("", "127.0.0.1", 0, "cpu")
    assert argv[:4] == [sys.executable, "-s", "-m", "scenesort.backend.commands"]
    assert argv[4:] == ["serve", "--host", "127.0.0.1", "--port", "0", "--exit-with-stdin",
                        "--device", "cpu"]  # fmt: skip
    assert service.engine_root() == REPO  # here the checkout; in Blender the wheels' folder
    env = service.child_env("", "secret")
    assert env["PYTHONPATH"] == str(REPO) and "PYTHONHOME" not in env
    assert env["SCENESORT_TOKEN"] == "secret"
    # An override of the user's own runs in the user's environment, path included.
    assert service.child_env(SLEEPER, "t").get("PYTHONPATH") == os.environ.get("PYTHONPATH")


def test_a_folder_named_backend_where_blender_runs_is_not_the_engine(tmp_path) -> None:
    """Many projects have a `backend/` (and a `kernels/`) of their own: run from such a
    folder (on `sys.path` first, as a script's folder is), the add-on still finds the
    engine by its one import name, `scenesort`."""
    for name in ("backend", "kernels"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "__init__.py").write_text("raise ImportError('not the engine')\n")
        (tmp_path / name / "commands").mkdir()
        (tmp_path / name / "commands" / "__main__.py").write_text("")
    code = ("import sys; sys.path.insert(0, ''); sys.path.append(sys.argv[1]);"
            "from addon import service; print(service.engine_root())")
    out = subprocess.run([sys.executable, "-c", code, str(REPO)], cwd=tmp_path,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == str(REPO)


def test_default_launch_without_the_engine_explains(monkeypatch) -> None:
    monkeypatch.setattr(service, "ENGINE_PACKAGE", "scenesort_no_such_engine")
    with pytest.raises(service.LaunchError, match="not installed beside the add-on"):
        service.command_line("", "127.0.0.1", 0)
