"""The Warp devices of this computer, found once by a short child process and cached.

The local service's Device preference defaults to the first CUDA device where there is
one. Finding it means importing Warp, which Blender's own process never does, so a child
(Blender's Python with the bundled engine's path, as the service runs) lists the devices
once: at enable in Blender's UI (on a thread, so that the Device menu lists the GPUs
before the first render), else when first needed. The answer is kept in Blender's config
folder with the engine's folder and Warp's version, so only a new engine probes again.
macOS has no CUDA: Warp runs on the CPU there, and nothing is probed. With a service
command of your own nothing is probed either: the Device menu lists what that service
reports.
"""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
import threading
from pathlib import Path

import bpy

from . import service, winjob

PROBE = (
    "import json, warp; warp.config.quiet = True; warp.init(); "
    "print(json.dumps([d.alias for d in warp.get_devices()]))"
)
PROBE_TIMEOUT_S = 120.0  # a first CUDA initialisation can take long; never hangs Blender
MACOS_REASON = "Warp has no GPU device on macOS: the service renders on the CPU"

_found: list[str] | None = None
_lock = threading.Lock()


def cache_path() -> Path:
    return Path(bpy.utils.user_resource("CONFIG", path="scenesort")) / "devices.json"


def _key(root: Path) -> list:
    """What the answer depends on: the interpreter, the engine's folder, Warp's wheel."""
    return [sys.executable, str(root), sorted(p.name for p in root.glob("warp_lang-*"))]


def _probe(root: Path) -> list[str] | None:
    """The devices Warp finds in a child process; None if the probe failed."""
    try:
        proc = subprocess.run(
            [sys.executable, "-s", "-c", PROBE], cwd=root, env=service.child_env("", None),
            capture_output=True, text=True, timeout=PROBE_TIMEOUT_S,
            creationflags=winjob.CREATE_NO_WINDOW if sys.platform == "win32" else 0,
        )  # fmt: skip
        devices = json.loads(proc.stdout.strip().splitlines()[-1]) if proc.returncode == 0 else 0
    except (OSError, subprocess.TimeoutExpired, ValueError, IndexError):
        return None
    if not isinstance(devices, list) or "cpu" not in devices:
        return None
    return [str(d) for d in devices]


def _cached_or_probed(path: Path) -> list[str]:
    root = service.engine_root()
    if sys.platform == "darwin" or root is None:
        return ["cpu"]
    key = _key(root)
    with contextlib.suppress(OSError, ValueError, KeyError, TypeError):
        cached = json.loads(path.read_text(encoding="utf-8"))
        if cached["key"] == key:
            return [str(d) for d in cached["devices"]]
    devices = _probe(root)
    if devices is None:
        return ["cpu"]  # not cached: a later session tries again
    with contextlib.suppress(OSError):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps({"key": key, "devices": devices}), encoding="utf-8")
    return devices


def found(path: Path | None = None) -> list[str]:
    """This computer's Warp devices ('cpu', 'cuda:0', ...), probed at the first call;
    `path`: the cache file (default `cache_path()`)."""
    global _found
    with _lock:
        if _found is None:
            _found = _cached_or_probed(path or cache_path())
        return list(_found)


def find_soon() -> threading.Thread:
    """`found()` on a daemon thread, the cache's path taken here, on Blender's main
    thread (bpy is not called from another one)."""
    thread = threading.Thread(target=found, args=(cache_path(),), daemon=True,
                              name="scenesort device probe")  # fmt: skip
    thread.start()
    return thread


def known() -> list[str]:
    """The devices found so far, without waiting for a probe (for drawing the menu)."""
    return list(_found or ["cpu"])


def default() -> str:
    """The first CUDA device, else the CPU."""
    return next((d for d in found() if d.startswith("cuda")), "cpu")


def forget() -> None:
    """Drop the answer of this session (the cache file stays)."""
    global _found
    with _lock:
        _found = None
