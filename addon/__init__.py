"""scenesort: ambient-occlusion renders and BVH build timings from a local Warp service.

The render engine `scenesort AO` (engine.py) renders F12 and animations; the panel
shows the build timings and a quick-look Render AO. A Blender extension (4.2+;
settings in blender_manifest.toml, no bl_info). In Blender's process it uses only the
standard library and numpy, and talks HTTP to `scenesort serve`, which it starts as a
child of Blender's own Python from the engine wheels the extension zip installed.
Relative imports only, so it also registers when imported as a plain package.
"""

from __future__ import annotations

import bpy

from . import animation, devices, engine, operators, panel, prefs, props, service

_MODULES = (prefs, props, operators, engine, panel, animation)


def interactive() -> bool:
    """Blender with its UI, where someone may open the Device menu before rendering."""
    return not bpy.app.background


def register() -> None:
    for module in _MODULES:
        module.register()
    if interactive():  # headless scripts probe when a render first needs the device
        devices.find_soon()


def unregister() -> None:
    service.stop()  # never leave the child service running without its add-on
    for module in reversed(_MODULES):
        module.unregister()
