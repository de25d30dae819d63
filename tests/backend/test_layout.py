"""The service's package layout (docs/architecture.md): every module of `scenesort.backend` is
in one of its packages; a package imports only the packages below it and no private name of
another; only render/ (and the packaging tools, which measure the engine against its peers)
imports the engine; no module reaches itself through its imports, those inside functions
included; no function is over 120 lines."""

from __future__ import annotations

import ast
import graphlib
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2] / "backend"
PREFIX = "scenesort.backend"
# package -> the packages it may import (wire/ and work/ stand on nothing of the service)
BELOW: dict[str, set[str]] = {
    "wire": set(),
    "work": set(),
    "render": {"wire", "work"},
    "api": {"wire", "work", "render"},
    "commands": {"wire", "work", "render", "api"},
    "tools": {"wire", "work", "render"},
}
ENGINE = ("scenesort.kernels", "warp")
ENGINE_USERS = {"render", "tools"}
MAX_FUNCTION_LINES = 120
SOURCES = sorted(ROOT.rglob("*.py"))


def dotted(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join((PREFIX, *(parts[:-1] if parts[-1] == "__init__" else parts)))


def package(module: str) -> str | None:
    """The service package `module` belongs to (None: outside the service, or its root)."""
    parts = module.split(".")
    return parts[2] if module.startswith(PREFIX + ".") and len(parts) > 2 else None


@cache
def import_statements(path: Path) -> tuple[tuple[str, tuple[str, ...], int], ...]:
    """(module, names, line) of every import in the file, those inside functions too."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found += [(alias.name, (), node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0, f"{path}:{node.lineno}: a relative import"
            found.append((node.module or "", tuple(a.name for a in node.names), node.lineno))
    return tuple(found)


def label(path: Path) -> str:
    return str(path.relative_to(ROOT))


def test_every_module_is_in_a_package() -> None:
    """A new module goes into the package of its concept, not beside them."""
    loose = [label(p) for p in SOURCES if package(dotted(p)) is None and p.name != "__init__.py"]
    assert not loose
    assert {package(dotted(p)) for p in SOURCES} - {None} == set(BELOW)


@pytest.mark.parametrize("path", SOURCES, ids=label)
def test_packages_import_only_those_below_them(path: Path) -> None:
    own = package(dotted(path))
    for module, names, line in import_statements(path):
        other = package(module)
        if own is None or other is None or other == own:
            continue
        assert other in BELOW[own], f"{label(path)}:{line} ({own}) imports {module} ({other})"
        private = [n for n in names if n.startswith("_")]
        assert not private, f"{label(path)}:{line} imports private {private} from {module}"


@pytest.mark.parametrize("path", SOURCES, ids=label)
def test_only_render_and_the_tools_import_the_engine(path: Path) -> None:
    if package(dotted(path)) in ENGINE_USERS:
        return
    for module, _, line in import_statements(path):
        engine = [e for e in ENGINE if module == e or module.startswith(e + ".")]
        assert not engine, f"{label(path)}:{line} imports the engine ({module})"


def test_no_import_cycles() -> None:
    """`from scenesort.backend.x import y` counts as an import of x.y when y is a module."""
    modules = {dotted(p): p for p in SOURCES}
    graph = graphlib.TopologicalSorter()
    for name, path in modules.items():
        graph.add(name)
        for module, names, _ in import_statements(path):
            targets = [f"{module}.{n}" if f"{module}.{n}" in modules else module
                       for n in names or ("",)]
            for target in targets:
                if target in modules and target != name:
                    graph.add(name, target)
    try:
        graph.prepare()
    except graphlib.CycleError as exc:
        pytest.fail(f"import cycle: {' -> '.join(exc.args[1])}")


@pytest.mark.parametrize("path", SOURCES, ids=label)
def test_no_function_is_over_120_lines(path: Path) -> None:
    long = [f"{node.name} ({node.end_lineno - node.lineno + 1} lines)"
            for node in ast.walk(ast.parse(path.read_text()))
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
            and node.end_lineno - node.lineno + 1 > MAX_FUNCTION_LINES]
    assert not long, f"{label(path)}: {long}"
