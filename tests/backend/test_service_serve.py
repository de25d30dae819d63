"""`scenesort serve`: loopback by default, a token always unless --no-token (loopback
only), clear refusals."""

from __future__ import annotations

import os
import stat
import subprocess
import sys

import httpx
from scenesort.backend.commands.serve import is_loopback

REPO = __import__("pathlib").Path(__file__).resolve().parents[2]


def serve(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "scenesort.backend.commands", "serve", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_refuses_no_token_off_loopback() -> None:
    result = serve("--host", "0.0.0.0", "--port", "0", "--no-token")
    assert result.returncode == 2
    assert "refusing --no-token on 0.0.0.0" in result.stderr


def test_refuses_a_short_env_token() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "scenesort.backend.commands", "serve", "--port", "0"], cwd=REPO,
        capture_output=True, text=True, timeout=60, env={**os.environ, "SCENESORT_TOKEN": "abc"},
    )
    assert result.returncode == 2 and "at least 16" in result.stderr


def test_refuses_an_unknown_device() -> None:
    result = serve("--device", "cuda:7", "--port", "0")
    assert result.returncode == 2 and "--device 'cuda:7' is not available" in result.stderr


def test_a_taken_port_is_refused_in_words_also_with_a_lifeline() -> None:
    """As the add-on starts it (stdin a pipe it never writes): the refusal exits with
    status 2 and its message, not with an abort at shutdown (a thread reading stdin)."""
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        child = subprocess.Popen(
            [sys.executable, "-m", "scenesort.backend.commands", "serve", "--port", str(port),
             "--exit-with-stdin", "--no-token"], cwd=REPO, stdin=subprocess.PIPE,
            stderr=subprocess.PIPE, text=True)
        try:
            child.wait(60)  # stdin held open, as by Blender
            err = child.stderr.read()
        finally:
            child.kill()
            child.stdin.close()
            child.stderr.close()
    assert child.returncode == 2, err
    assert f"cannot bind 127.0.0.1:{port}" in err and "Fatal Python error" not in err


def test_loopback_detection() -> None:
    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.168.1.2")
    assert not is_loopback("myhost.example")


def test_token_from_the_environment_is_required(start_service) -> None:
    guarded = start_service()  # conftest passes a fresh $SCENESORT_TOKEN
    assert "token from $SCENESORT_TOKEN" in guarded.first_line
    url = f"{guarded.url}/v1/scenes/{'0' * 32}"
    open_probe = httpx.get(f"{guarded.url}/v1/health", timeout=10)
    assert open_probe.status_code == 200
    assert set(open_probe.json()) == {"status", "version", "warp_version"}  # nothing more
    refused = httpx.get(url, timeout=10)
    assert refused.status_code == 401 and refused.json()["parameter"] == "Authorization"
    wrong = httpx.get(url, headers={"Authorization": "Bearer nope"}, timeout=10)
    assert wrong.status_code == 401
    for scheme in ("Bearer", "bearer", "BEARER"):  # RFC 7235: the scheme is case-insensitive
        right = httpx.get(url, headers={"Authorization": f"{scheme} {guarded.token}"},
                          timeout=10)
        assert right.status_code == 404  # past the guard: the scene just is not there
    full = httpx.get(f"{guarded.url}/v1/health", headers=guarded.auth, timeout=10).json()
    assert full["device"] == "cpu" and "cache" in full


def test_generated_token_is_stored_for_the_user_only(start_service, tmp_path) -> None:
    """No $SCENESORT_TOKEN: serve makes one in $XDG_RUNTIME_DIR/scenesort/token (0600, in a
    0700 folder), names the file on its first line, and `scenesort token` prints it."""
    env = {"SCENESORT_TOKEN": None, "XDG_RUNTIME_DIR": str(tmp_path)}
    made = start_service(env=env)
    path = tmp_path / "scenesort" / "token"
    assert f"token in {path}" in made.first_line
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert stat.S_IMODE(path.parent.stat().st_mode) == 0o700
    printed = subprocess.run(
        [sys.executable, "-m", "scenesort.backend.commands", "token"], cwd=REPO,
        capture_output=True, text=True, timeout=60,
        env={k: v for k, v in {**os.environ, **env}.items() if v is not None},
    ).stdout.strip()
    assert printed == path.read_text().strip() and len(printed) >= 32
    url = f"{made.url}/v1/scenes/{'0' * 32}"
    assert httpx.get(url, timeout=10).status_code == 401
    assert httpx.get(url, headers={"Authorization": f"Bearer {printed}"},
                     timeout=10).status_code == 404


def test_a_readable_token_file_is_replaced(tmp_path, monkeypatch) -> None:
    """A token file others could read may have leaked: a new token replaces it."""
    from scenesort.backend.api import token_file

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    monkeypatch.delenv("SCENESORT_TOKEN", raising=False)
    first = token_file.stored_token()
    assert token_file.stored_token() == first  # kept across restarts
    token_file.token_path().chmod(0o644)
    second = token_file.stored_token()
    assert second != first and stat.S_IMODE(token_file.token_path().stat().st_mode) == 0o600


def test_no_token_on_loopback(start_service) -> None:
    open_service = start_service("--no-token")
    assert "no token" in open_service.first_line
    assert httpx.get(f"{open_service.url}/v1/scenes/{'0' * 32}", timeout=10).status_code == 404


def test_listening_socket_lets_asyncio_turn_nagle_off() -> None:
    """asyncio sets TCP_NODELAY only on IPPROTO_TCP sockets; without it each keep-alive
    answer waited ~40 ms for a delayed ACK (a regression seen with socket.create_server)."""
    import socket

    from scenesort.backend.commands.serve import _listen

    server = _listen(socket.AF_INET, "127.0.0.1", 0)
    with server, socket.create_connection(server.getsockname()) as client:
        accepted, _ = server.accept()
        with accepted:
            assert client.fileno() >= 0
            assert accepted.proto == socket.IPPROTO_TCP
