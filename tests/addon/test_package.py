"""The extension manifest, `scenesort addon-zip`, the zip installing as a package, and the
scenesort wheel the platform zips bundle (without the packaging tools)."""

from __future__ import annotations

import base64
import csv
import hashlib
import importlib
import io
import re
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import bpy
import pytest
from blender_scenes import BLENDER_EXT, REPO
from packaging.version import Version
from scenesort.backend.tools import addon_zip

ADDON = REPO / "addon"


def _manifest() -> dict:
    return tomllib.loads((ADDON / "blender_manifest.toml").read_text(encoding="utf-8"))


def test_manifest_has_the_required_fields() -> None:
    m = _manifest()
    assert m["schema_version"] == "1.0.0"
    assert m["id"] == "scenesort" and m["type"] == "add-on"
    assert m["blender_version_min"] == "4.2.0"
    assert m["license"] == ["SPDX:MIT"]
    for key in ("version", "name", "tagline", "maintainer"):
        assert isinstance(m[key], str) and m[key], key
    assert len(m["tagline"]) <= 64 and not m["tagline"].endswith((".", "!", "?"))
    assert "local scenesort service" in m["permissions"]["network"]


def test_no_bl_info_and_relative_imports_only() -> None:
    for path in ADDON.glob("*.py"):
        text = path.read_text(encoding="utf-8")
        assert re.search(r"^bl_info\s*=", text, re.MULTILINE) is None, path.name
        for line in text.splitlines():
            stripped = line.strip()
            # Absolute imports of our own modules would break inside bl_ext.<repo>.scenesort.
            assert not stripped.startswith(("from addon", "import addon")), (path.name, line)


@pytest.fixture(scope="module")
def built_zip(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("zip") / "scenesort.zip"
    proc = subprocess.run(
        [sys.executable, "-m", "scenesort.backend.commands", "addon-zip", "--output", str(out)],
        cwd=REPO, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    path, size = proc.stdout.strip().split("\t")
    assert path == str(out) and size.endswith(f"({out.stat().st_size:,} bytes)")
    return out


def test_zip_contents(built_zip: Path) -> None:
    names = set(zipfile.ZipFile(built_zip).namelist())
    expected = {p.name for p in ADDON.glob("*.py")} | {"blender_manifest.toml"}
    assert names == expected
    assert "__init__.py" in names and not any("__pycache__" in n for n in names)


def test_zip_is_reproducible(built_zip: Path, tmp_path: Path) -> None:
    again = addon_zip.build_zip(ADDON, tmp_path / "again.zip")
    assert again.read_bytes() == built_zip.read_bytes()


def test_blenders_validator_accepts_the_zip(built_zip: Path) -> None:
    proc = subprocess.run(
        [sys.executable, str(BLENDER_EXT), "validate", str(built_zip)],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_zip_registers_as_its_own_package(built_zip: Path, tmp_path: Path) -> None:
    """Unpacked under another package name (as Blender does: bl_ext.<repo>.scenesort)."""
    target = tmp_path / "pkgs" / "scenesort_unzipped"
    zipfile.ZipFile(built_zip).extractall(target)
    sys.path.insert(0, str(target.parent))
    try:
        module = importlib.import_module("scenesort_unzipped")
        bpy.ops.wm.read_factory_settings(use_empty=True)
        module.register()
        try:
            prefs = bpy.context.preferences.addons["scenesort_unzipped"].preferences
            assert prefs.port == 0 and prefs.server_url == ""
        finally:
            module.unregister()
    finally:
        sys.path.remove(str(target.parent))
        for name in [n for n in sys.modules if n.split(".")[0] == "scenesort_unzipped"]:
            del sys.modules[name]


def test_missing_source_fails_with_a_message(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "scenesort.backend.commands", "addon-zip",
         "--source", str(tmp_path)],
        cwd=REPO, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert proc.returncode == 1 and "no blender_manifest.toml" in proc.stderr


def test_no_intel_mac_zip_and_the_reason(tmp_path: Path) -> None:
    """Warp's last macOS x86_64 wheel is 1.9.1 (`pip download --platform
    macosx_11_0_x86_64 warp-lang==1.19.0` finds none): asking for that zip says so and
    what an Intel Mac can do instead, and writes nothing."""
    proc = subprocess.run(
        [sys.executable, "-m", "scenesort.backend.commands", "addon-zip",
         "--platform", "macos-x64", "-o", str(tmp_path)],
        cwd=REPO, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert proc.returncode == 2 and not any(tmp_path.iterdir())
    assert "no macOS x86_64 wheel after 1.9.1" in proc.stderr and "Service URL" in proc.stderr
    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
    (warp,) = [d for d in pyproject["project"]["dependencies"] if d.startswith("warp-lang==")]
    assert Version(warp.removeprefix("warp-lang==")) > Version("1.9.1")  # the reason holds


def test_addon_and_engine_have_one_version() -> None:
    """The add-on refuses a service of another version: the zip's two halves must agree."""
    from scenesort import backend

    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
    assert _manifest()["version"] == pyproject["project"]["version"] == backend.__version__


def test_platform_zip_refuses_versions_that_differ(tmp_path: Path) -> None:
    source = tmp_path / "addon"
    source.mkdir()
    text = (ADDON / "blender_manifest.toml").read_text(encoding="utf-8")
    newer = text.replace('\nversion = "', '\nversion = "9', 1)
    (source / "blender_manifest.toml").write_text(newer)
    (tmp_path / "pyproject.toml").write_text('[project]\nversion = "0.1.0"\n')
    proc = subprocess.run(
        [sys.executable, "-m", "scenesort.backend.commands", "addon-zip", "--platform", "linux-x64",
         "--source", str(source), "-o", str(tmp_path / "x.zip")],
        cwd=REPO, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert proc.returncode == 1 and "the add-on is version 9" in proc.stderr
    assert not (tmp_path / "x.zip").exists()


@pytest.fixture(scope="module")
def engine_wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The scenesort wheel every platform zip bundles, as `addon-zip --platform` builds it."""
    return addon_zip.engine_wheel(REPO, tmp_path_factory.mktemp("engine"))


@pytest.mark.slow
def test_the_bundled_wheel_leaves_the_packaging_tools_out(engine_wheel: Path) -> None:
    """addon-zip, bench and the peer tracers are a packager's: Blender gets the service."""
    with zipfile.ZipFile(engine_wheel) as wheel:
        names = wheel.namelist()
    packages = {n.rsplit("/", 1)[0] for n in names if n.endswith("/__init__.py")}
    assert {"scenesort/backend/commands", "scenesort/backend/api", "scenesort/kernels"} <= packages
    assert not [n for n in names if n.startswith(addon_zip.TOOLS_IN_WHEEL)]
    assert addon_zip.TOOLS_IN_WHEEL.rstrip("/") == "scenesort/backend/tools"


@pytest.mark.slow
def test_the_bundled_wheels_record_lists_exactly_its_files(engine_wheel: Path) -> None:
    """PEP 376/427: RECORD names every file of the wheel with its sha256 and size."""
    with zipfile.ZipFile(engine_wheel) as wheel:
        (record,) = [n for n in wheel.namelist() if n.endswith(".dist-info/RECORD")]
        rows = list(csv.reader(io.StringIO(wheel.read(record).decode())))
        assert {row[0] for row in rows} == set(wheel.namelist())
        for path, digest, size in rows:
            if path == record:
                assert digest == size == ""
                continue
            data = wheel.read(path)
            expected = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=")
            assert (digest, size) == (f"sha256={expected.decode()}", str(len(data))), path


@pytest.mark.slow
def test_the_bundled_wheel_installs_and_says_where_the_tools_are(
    engine_wheel: Path, tmp_path: Path
) -> None:
    target = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps",
                    "--no-index", "--target", str(target), str(engine_wheel)],
                   check=True, timeout=300)
    assert not (target / "scenesort" / "backend" / "tools").exists()
    # -S: no site-packages, so the scenesort found is the one just installed.
    code = ("import sys; sys.path.insert(0, sys.argv[1]); "
            "from scenesort.backend.commands import main; sys.exit(main(sys.argv[2:]))")
    for command in ("bench", "addon-zip"):
        proc = subprocess.run([sys.executable, "-S", "-c", code, str(target), command],
                              cwd=tmp_path, capture_output=True, text=True, timeout=60)
        assert proc.returncode == 2, proc.stderr
        assert f"scenesort {command}: this install has no packaging tools" in proc.stderr
        assert "run it from a scenesort checkout" in proc.stderr


# Which Python each Blender runs (bpy on the package index, docs/addon.md).
BLENDER_PYTHONS = {"4.2.0": "3.11", "4.2.23": "3.11", "4.5.15": "3.11", "5.0.1": "3.11",
                   "5.1.0": "3.13", "5.3.0": "3.13", "6.0.0": "3.13"}  # fmt: skip


def _version(text: str) -> tuple[int, ...]:
    return tuple(int(part) for part in text.split("."))


@pytest.mark.parametrize(("blender", "python"), BLENDER_PYTHONS.items())
def test_exactly_one_zip_installs_in_each_blender_and_it_is_for_its_python(
    blender: str, python: str
) -> None:
    """Each zip's manifest takes the Blender versions of its Python (max is exclusive, as
    Blender reads it), so no Blender installs wheels it cannot load."""
    text = (ADDON / "blender_manifest.toml").read_text(encoding="utf-8")
    takes = []
    for zip_python in addon_zip.PYTHON_VERSIONS:
        wheel = "fastapi-0.1-py3-none-any.whl"
        m = tomllib.loads(addon_zip.manifest_with_wheels(text, "linux-x64", zip_python, [wheel]))
        assert m["platforms"] == ["linux-x64"] and m["wheels"] == [f"./wheels/{wheel}"]
        assert m["id"] == "scenesort" and "network" in m["permissions"]  # the rest kept
        high = m.get("blender_version_max")
        if _version(m["blender_version_min"]) <= _version(blender) and (
            high is None or _version(blender) < _version(high)
        ):
            takes.append(zip_python)
    assert takes == [python]


@pytest.mark.parametrize(("python", "accepted", "refused"), [
    ("3.11", ["1.26.4"], ["2.2.6"]),
    ("3.13", ["2.2.0", "2.5.5"], ["1.26.4", "3.0.0"]),
])  # fmt: skip
def test_the_engines_numpy_requirement_holds_for_each_blender_python(
    python: str, accepted: list[str], refused: list[str]
) -> None:
    """The scenesort wheel's numpy requirement (pyproject's), per Python: Blender 4.2-5.0
    bring numpy 1.26, 5.1 and later numpy 2 (bpy requires >= 2.2)."""
    from packaging.requirements import Requirement

    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
    env = {"python_version": python, "python_full_version": f"{python}.0", "extra": ""}
    reqs = [Requirement(d) for d in pyproject["project"]["dependencies"]]
    (numpy,) = [r for r in reqs if r.name == "numpy" and r.marker.evaluate(env)]
    assert all(numpy.specifier.contains(v) for v in accepted)
    assert not any(numpy.specifier.contains(v) for v in refused)


def test_zip_names_say_platform_and_python() -> None:
    m = _manifest()
    assert addon_zip.zip_name(m) == f"scenesort-{m['version']}.zip"
    platform_zip = addon_zip.zip_name(m, "linux-x64", "3.13")
    assert platform_zip == f"scenesort-{m['version']}-linux-x64-cp313.zip"
