"""Which RNA properties and functions the add-on names exist in this Blender: run by
tests/addon/test_extension_install.py with each Blender's own Python (bpy only).

Every attribute name and string constant in the add-on's sources (`obj.hide_render`,
`foreach_get("co", ...)`, `layout.prop(rd, "film_transparent")`) is looked up on the
Blender types the add-on reads (STRUCTS); the JSON printed maps each type to the names it
has, and "app" to the `bpy.app` members it reads. The test compares two Blenders' answers.
Usage: python rna_audit.py ADDON_DIR
"""

from __future__ import annotations

import ast
import json
import sys
from pathlib import Path

import bpy

# The types whose properties the add-on reads or writes (export, camera and its depth of
# field, engine, panel, preferences, operators). Cycles' own settings (scene.cycles) are
# an add-on's property group, looked up with getattr where read (pipeline.film_filter).
STRUCTS = (
    "Addon", "AddonPreferences", "Area", "BlendData", "Camera", "CameraDOFSettings",
    "Collection", "Context",
    "Depsgraph", "DepsgraphObjectInstance", "Image", "LayerCollection", "Mesh",
    "MeshLoopTriangle", "MeshVertex", "Object", "Operator", "Panel", "Preferences",
    "RenderEngine", "RenderLayer", "RenderPass", "RenderResult", "RenderSettings", "Scene",
    "UILayout", "ViewLayer", "Window", "WindowManager", "World", "WorldLighting",
)  # fmt: skip


def addon_names(addon: Path) -> tuple[set[str], set[str]]:
    """Attribute names and string constants in the add-on's Python files, and the names
    it reads from `bpy.app` (`bpy.app.X`)."""
    names: set[str] = set()
    app: set[str] = set()
    for path in addon.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Attribute):
                names.add(node.attr)
                if ast.unparse(node.value) == "bpy.app":
                    app.add(node.attr)
            elif isinstance(node, ast.Constant) and isinstance(node.value, str):
                names.add(node.value)
    return names, app


def audit(addon: Path) -> dict[str, list[str]]:
    """{type: the add-on's names that are its RNA properties or functions}, and "app"."""
    names, app = addon_names(addon)
    found = {}
    for struct in STRUCTS:
        rna = getattr(bpy.types, struct).bl_rna
        members = {p.identifier for p in rna.properties} | {f.identifier for f in rna.functions}
        found[struct] = sorted(names & members)
    found["app"] = sorted(n for n in app if hasattr(bpy.app, n))
    return found


if __name__ == "__main__":
    bpy.ops.wm.read_factory_settings(use_empty=True)
    print(json.dumps(audit(Path(sys.argv[1]))))
