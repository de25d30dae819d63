"""The `scenesort` command line: one subcommand per module, each owning its options."""

from __future__ import annotations

import argparse
import importlib
import sys
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from scenesort.ao_options import AoOptions

# name -> (module that implements it, one-line help). Each module defines
# `add_arguments(parser)` and `run(args) -> int`; importing is lazy so that
# `scenesort --help` does not pay for Warp or FastAPI.
COMMANDS: dict[str, tuple[str, str]] = {
    "render": ("scenesort.backend.commands.render",
               "render a scene (default: the built-in scene) and print timings"),
    "bake": ("scenesort.backend.commands.bake",
             "bake ambient occlusion into a texture of a mesh with UVs (no Blender)"),
    "render-frames": ("scenesort.backend.commands.render_frames",
                      "render a frame bundle (File > Export > scenesort animation)"),
    "bench": ("scenesort.backend.tools.bench",
              "build and trace a scene with every engine and peer, print a table"),
    "serve": ("scenesort.backend.commands.serve", "run the local HTTP service (FastAPI + uvicorn)"),
    "addon-zip": ("scenesort.backend.tools.addon_zip",
                  "build the installable Blender extension zip"),
    "addon-options": ("scenesort.backend.tools.addon_options",
                      "write addon/ao_options.py, the add-on's copy of the AO settings"),
    "token": ("scenesort.backend.commands.token",
              "print the token `scenesort serve` uses (clients send it)"),
}
TOOLS = "scenesort.backend.tools"  # left out of the wheel the Blender extension bundles


def add_ao_option(parser: Any, name: str) -> None:
    """The flag of the AO setting `name` (--target-error for target_error), as AoOptions
    defines it (scenesort/ao_options.py): its type, default, choices and help; a bool is a
    switch."""
    from scenesort.ao_options import AO_OPTIONS

    spec = AO_OPTIONS[name]
    flag = "--" + name.replace("_", "-")
    shown = "" if spec.default is None or spec.kind is bool else f" (default {spec.default})"
    help_text = spec.doc.replace("%", "%%") + shown
    if spec.kind is bool:
        parser.add_argument(flag, action="store_true", help=help_text)
    else:
        parser.add_argument(flag, type=spec.kind, default=spec.default, choices=spec.choices,
                            help=help_text)


def ao_options(args: argparse.Namespace, **more: Any) -> AoOptions:
    """AoOptions of the AO flags in `args` (and `more`), checked there; ValueError naming
    the flag at fault and the fix."""
    from scenesort.ao_options import AO_OPTIONS, AoOptions, OptionError

    given = {name: getattr(args, name) for name in AO_OPTIONS if hasattr(args, name)}
    try:
        return AoOptions(**given, **more)
    except OptionError as exc:
        raise ValueError(f"--{exc.name.replace('_', '-')}: {exc} ({exc.fix})") from None


def check_at_least(args: argparse.Namespace, minimum: int, *names: str) -> None:
    """ValueError naming the first option among `names` that is set and below `minimum`."""
    for name in names:
        value = getattr(args, name)
        if value is not None and value < minimum:
            raise ValueError(f"--{name.replace('_', '-')} must be >= {minimum}, got {value}")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(prog="scenesort", description=__doc__)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, help_text) in COMMANDS.items():
        sub.add_parser(name, help=help_text, add_help=False)
    # Parse the command name first, then hand the rest to the owning module's parser.
    name = next((a for a in argv if not a.startswith("-")), None)
    if name not in COMMANDS:
        parser.print_help() if name is None else parser.error(f"unknown command {name!r}")
        return 0 if name is None else 2
    try:
        module = importlib.import_module(COMMANDS[name][0])
    except ModuleNotFoundError as exc:
        if exc.name is None or not exc.name.startswith(TOOLS):
            raise
        print(f"scenesort {name}: this install has no packaging tools (the Blender "
              "extension's wheel leaves them out); run it from a scenesort checkout "
              "(pip install -e .)", file=sys.stderr)
        return 2
    cmd_parser = argparse.ArgumentParser(prog=f"scenesort {name}", description=COMMANDS[name][1])
    module.add_arguments(cmd_parser)
    args = cmd_parser.parse_args(argv[argv.index(name) + 1 :])
    return int(module.run(args) or 0)
