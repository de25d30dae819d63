"""The engine's package layout (docs/architecture.md): each package of `kernels` imports only
the packages below it, never a private name of another package, and no module imports
itself through others (no import cycles)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

pytestmark = pytest.mark.host_only  # the source files

ROOT = Path(__file__).resolve().parents[2] / "kernels"
# a package may import from the packages before it in this order
ORDER = ("core", "pool", "bvh", "dacrt", "scene", "render")
ALLOWED = {
    "core": set(),
    "pool": {"core"},
    "bvh": {"core", "pool"},
    "dacrt": {"core", "pool"},
    "scene": {"core", "pool", "bvh", "dacrt"},
    "render": {"core", "pool", "bvh", "dacrt", "scene"},
}
MODULES = sorted(p for p in ROOT.rglob("*.py"))


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path, top_level: bool = False) -> list[tuple[str, list[str]]]:
    """(absolute module, imported names) of every import in the file (only those that run
    when the module is imported, with `top_level`)."""
    package = module_name(path) if path.name == "__init__.py" else module_name(path).rsplit(
        ".", 1)[0]
    tree = ast.parse(path.read_text())
    out = []
    for node in (tree.body if top_level else ast.walk(tree)):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            out.append((target, [a.name for a in node.names]))
        elif isinstance(node, ast.Import):
            out.extend((a.name, []) for a in node.names)
    return out


def package_of(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "kernels" and parts[1] in ORDER else None


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(ROOT)))
def test_packages_import_only_those_below_them(path):
    own = package_of(module_name(path))
    for target, names in imports(path):
        other = package_of(target)
        if own is None or other is None or other == own:  # the facade may import any
            continue
        assert other in ALLOWED[own], f"kernels.{own} imports {target} (kernels.{other})"
        private = [n for n in names if n.startswith("_")]
        assert not private, f"{module_name(path)} imports private {private} from {target}"


def test_facade_imports_no_private_names():
    for target, names in imports(ROOT / "__init__.py"):
        assert not [n for n in names if n.startswith("_")], target


def test_no_import_cycles():
    """The graph of module-level imports between engine modules has no cycle."""
    modules = {module_name(p): p for p in MODULES}
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        edges = set()
        for target, names in imports(path, top_level=True):
            for n in names or [""]:
                sub = f"{target}.{n}" if n else target
                hit = sub if sub in modules else target
                if hit in modules and hit != name:
                    edges.add(hit)
        graph[name] = edges
    state: dict[str, int] = {}  # 1: on the path, 2: done

    def visit(n: str, path: list[str]) -> None:
        state[n] = 1
        for m in sorted(graph[n]):
            if state.get(m) == 1:
                raise AssertionError("import cycle: " + " -> ".join([*path, n, m]))
            if m not in state:
                visit(m, [*path, n])
        state[n] = 2

    for n in sorted(graph):
        if n not in state:
            visit(n, [])
