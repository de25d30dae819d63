"""One import name: the distribution installs one top-level package, `scenesort`, with every
engine and service package in it (Blender's extensions share one site-packages, where a
top-level `kernels` or `backend` would collide with another extension's), and no code of
the project imports the folders by their own names."""

from __future__ import annotations

import re
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet",
                    "--wheel-dir", str(out), str(REPO)], check=True, timeout=600)
    (path,) = out.glob("scenesort-*.whl")
    return path


def source_packages() -> set[str]:
    """Every package folder of kernels/ and backend/, by the name it installs under."""
    names = {"scenesort"}
    for folder in ("kernels", "backend"):
        for init in (REPO / folder).rglob("__init__.py"):
            parts = init.parent.relative_to(REPO).parts
            names.add(".".join(("scenesort", *parts)))
    return names


@pytest.mark.slow
def test_the_only_top_level_entry_is_scenesort(wheel: Path) -> None:
    with zipfile.ZipFile(wheel) as zf:
        top = {name.split("/")[0] for name in zf.namelist()}
    assert top == {"scenesort", f"{wheel.name.split('-')[0]}-{wheel.name.split('-')[1]}"
                                ".dist-info"}


@pytest.mark.slow
def test_every_package_folder_is_in_the_wheel(wheel: Path) -> None:
    with zipfile.ZipFile(wheel) as zf:
        packages = {name.rsplit("/", 1)[0].replace("/", ".") for name in zf.namelist()
                    if name.endswith("/__init__.py")}
    assert packages == source_packages()


@pytest.mark.slow
def test_every_file_the_engine_reads_is_in_the_wheel(wheel: Path) -> None:
    """The files beside the modules that they read at import (bvh/wide_simd.h, the SIMD
    traversal's C++): without one the engine fails on import."""
    wanted = {"/".join(("scenesort", *p.relative_to(REPO).parts))
              for folder in ("kernels", "backend") for p in (REPO / folder).rglob("*")
              if p.is_file() and p.suffix not in (".py", ".pyc")
              and "__pycache__" not in p.parts}
    assert "scenesort/kernels/bvh/wide_simd.h" in wanted
    with zipfile.ZipFile(wheel) as zf:
        assert wanted <= set(zf.namelist())


@pytest.mark.slow
def test_the_command_line_is_scenesorts(wheel: Path) -> None:
    with zipfile.ZipFile(wheel) as zf:
        (entry,) = [n for n in zf.namelist() if n.endswith("entry_points.txt")]
        text = zf.read(entry).decode()
    assert "scenesort = scenesort.backend.commands:main" in text


# an import statement naming `kernels` or `backend` first: in code, or in code that a test
# hands to a child process as a string
FOLDER_IMPORT = re.compile(r"^\s*(from\s+(kernels|backend)\b|import\s+"
                           r"([\w.]+(\s+as\s+\w+)?\s*,\s*)*(kernels|backend)\b)", re.M)


def test_no_code_imports_kernels_or_backend_by_the_folder_name() -> None:
    """From the repository's root `import kernels` would work, and load a second copy of
    the engine beside `scenesort.kernels` (a test once patched the wrong one)."""
    bad = []
    for path in REPO.rglob("*.py"):
        if any(part.startswith(".") or part == "build" for part in path.relative_to(REPO).parts):
            continue
        text = path.read_text()
        bad += [f"{path.relative_to(REPO)}:{text.count(chr(10), 0, m.start()) + 1}"
                for m in FOLDER_IMPORT.finditer(text)]
    assert not bad, bad
