"""The service's bearer token: from $SCENESORT_TOKEN, else a file only the user can read.

Like Jupyter's server, `scenesort serve` always has a token unless told `--no-token`
(loopback only). The generated one is kept in `token` under the user's runtime
directory ($XDG_RUNTIME_DIR, a per-user tmpfs on Linux), else the config directory
($XDG_CONFIG_HOME or ~/.config), in a folder of mode 0700 and a file of mode 0600, so
other local users cannot read it; `scenesort token` prints it for clients. A token never
goes on a command line, where `ps` shows it to everyone. The Blender add-on keeps the token
of a service of your own with the same two functions (`read_private`, `write_private`).
"""

from __future__ import annotations

import os
import secrets
import stat
from pathlib import Path

TOKEN_ENV = "SCENESORT_TOKEN"
MIN_TOKEN_CHARS = 16  # a shorter $SCENESORT_TOKEN is guessable; refuse it


def token_dir() -> Path:
    """Where the generated token lives: the runtime directory if there is one, else config."""
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    if runtime and Path(runtime).is_dir():
        return Path(runtime) / "scenesort"
    config = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(config) / "scenesort"


def token_path() -> Path:
    return token_dir() / "token"


def _private(path: Path) -> bool:
    """Whether `path` is a regular file of ours that nobody else can read or write."""
    try:
        info = path.lstat()
    except FileNotFoundError:
        return False
    if os.name == "nt":  # no mode bits: a user's profile folders are private by their ACL
        return stat.S_ISREG(info.st_mode)
    return stat.S_ISREG(info.st_mode) and info.st_uid == os.getuid() and not info.st_mode & 0o077


def read_private(path: Path) -> str | None:
    """The stripped text of `path` if only this user can read or write it, else None."""
    return path.read_text(encoding="utf-8").strip() if _private(path) else None


def write_private(path: Path, text: str) -> None:
    """Write `text` to `path` as a file of mode 0600 in a folder of mode 0700, atomically:
    a reader sees the old text or the new, whole."""
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    os.chmod(path.parent, 0o700)  # mkdir's mode is masked, and the folder may be older
    fresh = path.with_name(f".{path.name}-{secrets.token_hex(8)}")
    fd = os.open(fresh, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as out:
        out.write(text + "\n")
    os.replace(fresh, path)


def stored_token() -> str:
    """The token in the user's token file, made (0600, in a 0700 folder) if there is none.

    A file that others could read, or that is not a plain file of this user, is replaced:
    its token may have leaked."""
    path = token_path()
    token = read_private(path)
    if token is not None and len(token) >= MIN_TOKEN_CHARS:
        return token
    token = secrets.token_urlsafe(32)
    write_private(path, token)
    return token


def service_token() -> tuple[str, str]:
    """(token, where it came from) for `scenesort serve`; ValueError for a weak env token."""
    env = os.environ.get(TOKEN_ENV)
    if env is not None:
        if len(env) < MIN_TOKEN_CHARS:
            raise ValueError(
                f"${TOKEN_ENV} is {len(env)} characters; use at least {MIN_TOKEN_CHARS} "
                "(e.g. python -c 'import secrets; print(secrets.token_urlsafe(32))')"
            )
        return env, f"${TOKEN_ENV}"
    return stored_token(), str(token_path())
