"""Add-on preferences: where the service is, how the local one starts, on which device.

Kept in the user's preferences, never in a .blend: a file someone sends you cannot
choose where your geometry goes or which program Blender runs. The service token is not
even in the preferences file: it lives in a file only the user can read, in Blender's
config folder, written by the engine's token_file (as the service keeps its own token).
"""

from __future__ import annotations

import contextlib
import os
import sys
from pathlib import Path

import bpy
from bpy.props import BoolProperty, EnumProperty, IntProperty, StringProperty

from . import devices, service
from .connection import Target, check_remote

# Scripts and tests can point at another launcher with this variable when the
# preference is empty.
COMMAND_ENV = "SCENESORT_COMMAND"
LEGACY_COMMAND = "scenesort"  # the old default ('scenesort' on PATH): now means "unset"

# Devices the service reported (`devices` of its health answer); Blender needs the
# enum items kept alive on the Python side while they are shown.
_reported: list[str] = []
_items: list[tuple[str, str, str, int]] = []
_session_token = ""  # where the token lives without the bundled engine: this session only


def token_path() -> Path:
    """The file of the token of a service of your own (mode 0600, folder 0700)."""
    return Path(bpy.utils.user_resource("CONFIG", path="scenesort")) / "service-token"


def _token_file():  # noqa: ANN202 - the module, or None
    """The engine's private-file functions (backend/api/token_file.py, standard library
    only); None when the extension was installed without the engine."""
    try:
        from scenesort.backend.api import token_file
    except ImportError:
        return None
    return token_file


def _get_token(self) -> str:  # noqa: ANN001
    store = _token_file()
    if store is not None:
        with contextlib.suppress(OSError, ValueError):  # unreadable: as if none were saved
            saved = store.read_private(token_path())
            if saved is not None:
                return saved
    return _session_token


def _set_token(self, value: str) -> None:  # noqa: ANN001
    global _session_token
    _session_token = value.strip()
    store = _token_file()
    if store is None:
        return
    try:
        if _session_token:
            store.write_private(token_path(), _session_token)
        else:
            token_path().unlink(missing_ok=True)
    except OSError as exc:  # a read-only config folder: the token lasts this session
        print(f"scenesort: the service token could not be saved in {token_path()}: {exc}")


def remember_devices(health: dict) -> None:
    """Keep the Warp devices of a health answer for the Device menu."""
    devices = health.get("devices")
    if isinstance(devices, list):
        _reported[:] = [str(d) for d in devices if str(d) != "cpu"]


def chosen_device(prefs: SCENESORT_AP_preferences, wait: bool = True) -> str:
    """The local service's device: the one chosen, else the first CUDA device found (the
    probe runs once, devices.py), else the CPU. `wait=False` (drawing): no probe."""
    if prefs.device_name:
        return prefs.device_name
    if wait:
        return devices.default()
    return next((d for d in devices.known() if d.startswith("cuda")), "cpu")


def _device_items(self, context):  # noqa: ANN001, ANN202 - Blender's callback signature
    names = list(dict.fromkeys(["cpu", *devices.known(), *_reported]))
    chosen = chosen_device(self, wait=False)
    if chosen not in names:
        names.append(chosen)  # chosen in an earlier session: keep showing it
    cpu = devices.MACOS_REASON if sys.platform == "darwin" else "Warp device cpu"
    _items[:] = [
        (name, "CPU" if name == "cpu" else name.upper().replace(":", " "),
         cpu if name == "cpu" else f"Warp device {name}", i)
        for i, name in enumerate(names)
    ]  # fmt: skip
    return _items


def _get_device(self) -> int:  # noqa: ANN001
    names = [item[0] for item in _device_items(self, None)]
    return names.index(chosen_device(self, wait=False))


def _set_device(self, value: int) -> None:  # noqa: ANN001
    before = chosen_device(self, wait=False)
    self.device_name = _device_items(self, None)[value][0]
    if self.device_name != before and service.running():
        # The running service keeps its device: stop it, and the next render (or Start
        # Local Service) starts it on the new one.
        service.stop()


class SCENESORT_AP_preferences(bpy.types.AddonPreferences):
    """The scenesort service: local (started by Blender) or one of your own."""

    bl_idname = __package__

    device: EnumProperty(  # type: ignore[valid-type]
        name="Device",
        description=(
            "Warp device of the local service: by default the first CUDA device found, "
            "else the CPU. Choosing another stops the running local service; the next "
            "render starts it on the new device"
        ),
        items=_device_items,
        get=_get_device,
        set=_set_device,
    )
    # Empty: not chosen, the first CUDA device found (chosen_device).
    device_name: StringProperty(default="", options={"HIDDEN"})  # type: ignore[valid-type]
    port: IntProperty(  # type: ignore[valid-type]
        name="Port",
        description="TCP port of the local service on 127.0.0.1 (0: a free one at each start)",
        default=0,
        min=0,
        max=65535,
    )
    start_on_render: BoolProperty(  # type: ignore[valid-type]
        name="Start the service on first render",
        description="Build BVH and Render AO start the local service when none runs",
        default=True,
    )
    server_url: StringProperty(  # type: ignore[valid-type]
        name="Service URL",
        description=(
            "A scenesort service you run yourself, e.g. http://127.0.0.1:8765 "
            "(empty: the local service that Blender starts)"
        ),
        default="",
    )
    server_token: StringProperty(  # type: ignore[valid-type]
        name="Service token",
        description=(
            "The token of the service at Service URL ('scenesort token' prints it there); "
            "kept in a file only you can read, never in Blender's preferences file. The "
            "local service needs none"
        ),
        subtype="PASSWORD",
        get=_get_token,
        set=_set_token,
    )
    allow_remote: BoolProperty(  # type: ignore[valid-type]
        name="Allow a remote service",
        description=(
            "Let Service URL name another computer, which then receives your scene's "
            "geometry (needs Blender's Allow Online Access too)"
        ),
        default=False,
    )
    server_command: StringProperty(  # type: ignore[valid-type]
        name="Service command",
        description=(
            "Override: a program that runs the service, e.g. '/path/to/.venv/bin/scenesort' "
            "('serve --host ... --port ... --device ...' is added; quote paths with spaces). "
            "Empty: Blender's own Python runs the engine installed with the extension"
        ),
        default="",
    )

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        col = layout.column(heading="Local service")
        col.prop(self, "device")
        col.prop(self, "port")
        col.prop(self, "start_on_render")
        col.prop(self, "server_command")
        col.operator("scenesort.open_log", icon="TEXT")
        col = layout.column(heading="Own service")
        col.prop(self, "server_url")
        col.prop(self, "server_token")
        col.prop(self, "allow_remote")


def preferences(context: bpy.types.Context) -> SCENESORT_AP_preferences:
    """This add-on's preferences."""
    return context.preferences.addons[__package__].preferences


def server_command(prefs: SCENESORT_AP_preferences) -> str:
    """The launcher override: the preference if set, else $SCENESORT_COMMAND, else ''
    (Blender's own Python runs the bundled engine)."""
    value = prefs.server_command.strip()
    if value and value != LEGACY_COMMAND:
        return value
    return os.environ.get(COMMAND_ENV, "").strip()


def target(context: bpy.types.Context, start: bool | None = None) -> Target:
    """Where requests go, checked (a remote URL only when allowed); `start` overrides
    'Start the service on first render'."""
    prefs = preferences(context)
    url = prefs.server_url.strip()
    if url:
        check_remote(url, prefs.allow_remote, bool(bpy.app.online_access))
    return Target(
        url=url,
        token=prefs.server_token.strip() if url else "",
        command=server_command(prefs),
        port=prefs.port,
        device=chosen_device(prefs, wait=not url),  # a service of your own: no probe
        start=prefs.start_on_render if start is None else start,
    )


# Set when the add-on is imported as a plain package (scripts, tests): Blender only
# creates an add-on entry, which holds the preferences, for add-ons it enables itself.
_own_entry = False


def register() -> None:
    global _own_entry
    bpy.utils.register_class(SCENESORT_AP_preferences)
    addons = bpy.context.preferences.addons
    if addons.get(__package__) is None:
        addons.new().module = __package__
        _own_entry = True


def unregister() -> None:
    global _own_entry
    if _own_entry:
        entry = bpy.context.preferences.addons.get(__package__)
        if entry is not None:
            bpy.context.preferences.addons.remove(entry)
        _own_entry = False
    bpy.utils.unregister_class(SCENESORT_AP_preferences)
