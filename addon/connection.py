"""Which service a request goes to: checked, version-matched, started when allowed.

Runs inside a `Task` (main thread or worker) from a `Target`, a snapshot of the add-on
preferences taken on the main thread. The local service is the child process that
`service.py` starts; a "Service URL" names a service of the user's own, which must be
on this computer unless remote services are allowed.
"""

from __future__ import annotations

import time
import tomllib
import urllib.parse
from dataclasses import dataclass
from pathlib import Path

from . import service
from .client import Client, ServiceError
from .tasks import Cancelled, Task

# The add-on's version: the service must report the same one.
ADDON_VERSION = tomllib.loads(
    Path(__file__).with_name("blender_manifest.toml").read_text(encoding="utf-8")
)["version"]
START_TIMEOUT_S = 120.0  # a first start imports Warp and FastAPI from a cold disk cache
POLL_S = 0.25
LOCAL_HOST = "127.0.0.1"


class VersionMismatch(ServiceError):
    """The service that answers is another scenesort version than the add-on."""


@dataclass(frozen=True)
class Target:
    """Where requests go, from the add-on preferences; safe to read off the main thread."""

    url: str = ""  # a service of the user's own; "" = the local one Blender starts
    token: str = ""  # the token of the service at `url` (the local one's is known)
    command: str = ""  # "Service command" override; "" = Blender's Python + bundled engine
    port: int = 0  # the local service's port; 0 = a free one at each start
    device: str = "cpu"  # the local service's Warp device
    start: bool = True  # start the local service when none answers


@dataclass
class Connection:
    """A client of a service that answered with the add-on's version."""

    client: Client
    health: dict
    started: bool  # this connection launched the service


def check_remote(url: str, allow_remote: bool, online_access: bool) -> str:
    """`url` if it may be used: on this computer, or remote when both the preference and
    Blender's online access allow it; ServiceError naming the setting otherwise."""
    host = urllib.parse.urlsplit(url.strip()).hostname or ""
    if not host or service.is_loopback(host):
        return url
    if not allow_remote:
        raise ServiceError(
            f"Service URL '{url}' is not on this computer: the scene would be sent to "
            f"{host}. Turn on 'Allow a remote service' in the add-on preferences to use it"
        )
    if not online_access:
        raise ServiceError(
            f"Service URL '{url}' is remote and Blender's online access is off: turn on "
            "Preferences > System > Network > Allow Online Access to use it"
        )
    return url


def check_version(health: dict, url: str) -> None:
    """VersionMismatch unless the service runs the add-on's version."""
    version = str(health.get("version", "?"))
    if version == ADDON_VERSION:
        return
    if service.running():
        fix = "press 'Restart Local Service'"
    else:
        fix = "stop it (or update it) and let the add-on start its own service"
    raise VersionMismatch(
        f"The service at {url} is scenesort {version} but the add-on is {ADDON_VERSION}: {fix}"
    )


def _checked(url: str, token: str = "") -> Connection:
    """A client of `url` whose health answer has the add-on's version (the one place
    where the add-on's clients are made; without `token`, the client sends the token
    of the service this add-on started, if it serves `url`)."""
    client = Client(url, token or None)
    health = client.health()
    check_version(health, url)
    return Connection(client, health, started=False)


def _wait_for_start(task: Task) -> Connection:
    """Poll our child until it answers; the step shows the time and its latest line."""
    started = time.monotonic()
    while True:
        if not service.running():
            raise service.LaunchError(f"The service did not start: {service.exit_message()}")
        url = service.served_url()
        if url is not None:
            try:
                return _checked(url)
            except VersionMismatch:
                raise
            except ServiceError:
                pass  # bound but not answering yet
        elapsed = time.monotonic() - started
        if elapsed > START_TIMEOUT_S:
            log = service.log_path()
            service.stop()
            raise service.LaunchError(
                f"The service did not answer within {START_TIMEOUT_S:g} s; its log is {log}"
            )
        line = service.last_log_line()[:80]
        task.set_step(f"starting the service, {elapsed:.0f} s" + (f": {line}" if line else ""))
        time.sleep(POLL_S)


def _startable(target: Target) -> bool:
    """Whether a missing service may be launched: allowed, and the URL is ours to start."""
    if not target.start:
        return False
    host = urllib.parse.urlsplit(target.url).hostname or ""
    return not target.url or service.is_loopback(host)


def connect(task: Task, target: Target) -> Connection:
    """A client of a service with the add-on's version; with `target.start`, launches the
    local service first when none answers (and waits for it, showing progress).

    The URL tried is the preference's, else our running child's, else the fixed port's.
    """
    task.set_step("connecting to the service")
    if service.running() and not target.url:
        return _wait_for_start(task)  # at once if it already answers
    url = target.url or (f"http://{LOCAL_HOST}:{target.port}" if target.port else None)
    if url is not None:
        try:
            return _checked(url, target.token)
        except VersionMismatch:
            raise
        except ServiceError:
            if not _startable(target) or service.running():
                raise
    elif not target.start:
        raise ServiceError(
            "No scenesort service is running: press 'Start Local Service', or turn on "
            "'Start the service on first render' in the add-on preferences"
        )
    service.start(target.command, url or f"http://{LOCAL_HOST}:0", target.device)
    try:
        connection = _wait_for_start(task)
    except Cancelled:
        service.stop()  # a start the user abandoned leaves nothing running
        raise
    connection.started = True
    return connection
