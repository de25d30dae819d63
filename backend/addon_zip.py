"""`scenesort addon-zip`: build the installable Blender extension zip from addon/.

The zip holds the extension's files at its root (blender_manifest.toml beside
__init__.py), as Blender's own `blender --command extension build` lays it out, so
Edit > Preferences > Get Extensions > Install from Disk accepts it. Entries carry a
fixed timestamp so the same sources give the same bytes.
"""

from __future__ import annotations

import argparse
import sys
import tomllib
import zipfile
from pathlib import Path

ADDON_DIR = Path(__file__).resolve().parents[1] / "addon"
MANIFEST = "blender_manifest.toml"
INCLUDE_SUFFIXES = {".py", ".toml"}
FIXED_DATE = (2024, 1, 1, 0, 0, 0)  # zip timestamps cannot predate 1980; any fixed value works


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `scenesort addon-zip`."""
    parser.add_argument(
        "--output",
        "-o",
        type=Path,
        default=None,
        help="zip file to write (default: build/scenesort-<version>.zip)",
    )
    parser.add_argument(
        "--source", type=Path, default=ADDON_DIR, help="the add-on folder (default: addon/)"
    )


def addon_files(source: Path) -> list[Path]:
    """The files that ship: sources and the manifest, no caches or editor leftovers."""
    files = [
        p
        for p in sorted(source.rglob("*"))
        if p.is_file()
        and p.suffix in INCLUDE_SUFFIXES
        and "__pycache__" not in p.parts
        and not any(part.startswith(".") for part in p.relative_to(source).parts)
    ]
    return files


def build_zip(source: Path, output: Path | None = None) -> Path:
    """Write the zip and return its path; ValueError if addon/ is not an extension."""
    manifest_path = source / MANIFEST
    if not manifest_path.is_file():
        raise ValueError(f"{source} has no {MANIFEST}: is it the add-on folder?")
    manifest = tomllib.loads(manifest_path.read_text(encoding="utf-8"))
    if output is None:
        output = Path("build") / f"{manifest['id']}-{manifest['version']}.zip"
    output.parent.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(output, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for path in addon_files(source):
            info = zipfile.ZipInfo(path.relative_to(source).as_posix(), FIXED_DATE)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, path.read_bytes())
    return output


def run(args: argparse.Namespace) -> int:
    try:
        path = build_zip(args.source, args.output)
    except (ValueError, OSError, KeyError, tomllib.TOMLDecodeError) as exc:
        print(f"scenesort addon-zip: {exc}", file=sys.stderr)
        return 1
    print(path)
    return 0
