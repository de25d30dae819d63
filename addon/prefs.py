"""Add-on preferences: which command starts the local service."""

from __future__ import annotations

import os

import bpy
from bpy.props import StringProperty

DEFAULT_COMMAND = "scenesort"
# Scripts and tests without enabled preferences (the add-on imported as a plain
# package) can point at another launcher with this variable.
COMMAND_ENV = "SCENESORT_COMMAND"


class SCENESORT_AP_preferences(bpy.types.AddonPreferences):
    """Kept in the user's preferences, never in a .blend, so a file cannot pick a program."""

    bl_idname = __package__

    server_command: StringProperty(  # type: ignore[valid-type]
        name="Service command",
        description=(
            "Program that runs the service, e.g. 'scenesort' on PATH or "
            "'/path/to/.venv/bin/scenesort'; 'serve --host ... --port ...' is added"
        ),
        default=DEFAULT_COMMAND,
    )

    def draw(self, context: bpy.types.Context) -> None:
        self.layout.prop(self, "server_command")


def server_command(context: bpy.types.Context) -> str:
    """The launcher command line: the preference if enabled, else $SCENESORT_COMMAND."""
    addon = context.preferences.addons.get(__package__)
    prefs = getattr(addon, "preferences", None)
    value = getattr(prefs, "server_command", "").strip()
    if value and value != DEFAULT_COMMAND:
        return value
    return os.environ.get(COMMAND_ENV, "").strip() or DEFAULT_COMMAND


def register() -> None:
    bpy.utils.register_class(SCENESORT_AP_preferences)


def unregister() -> None:
    bpy.utils.unregister_class(SCENESORT_AP_preferences)
