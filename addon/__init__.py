"""scenesort: ambient-occlusion renders and BVH build timings from a local Warp service.

The render engine `scenesort AO` (engine.py) renders F12 and animations; the panel
shows the build timings and a quick-look Render AO. A Blender extension (4.2+;
settings in blender_manifest.toml, no bl_info). In Blender's process it uses only the
standard library and numpy, and talks HTTP to `scenesort serve`, which it starts as a
child of Blender's own Python from the engine wheels the extension zip installed.
Relative imports only, so it also registers when imported as a plain package.
"""

from __future__ import annotations

from . import animation, engine, operators, panel, prefs, props, service

_MODULES = (prefs, props, operators, engine, panel, animation)


def register() -> None:
    for module in _MODULES:
        module.register()


def unregister() -> None:
    service.stop()  # never leave the child service running without its add-on
    for module in reversed(_MODULES):
        module.unregister()
