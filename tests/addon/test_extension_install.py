"""From a fresh Blender user directory: install the linux-x64 zip, render a frame.

A throw-away Python environment with only `bpy` (and what bpy itself needs: numpy,
as Blender ships it) runs tests/addon/install_and_render.py: Blender's own installer
puts the zip's wheels into the extensions' site-packages, and the add-on, with no
setting changed, no SCENESORT_COMMAND and no `scenesort` on PATH, starts the service
with that Python and renders. The image must equal a direct engine call made here.
"""

from __future__ import annotations

import json
import os
import platform
import re
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import numpy as np
import pytest
from blender_scenes import BLENDER_EXT, REPO

pytestmark = [
    pytest.mark.skipif(
        not (sys.platform.startswith("linux") and platform.machine() == "x86_64"),
        reason="installs the linux-x64 zip, which only this platform can run",
    ),
    pytest.mark.slow,  # builds the zips for every platform and a venv: ~25 s warm
]
SCRIPT = Path(__file__).with_name("install_and_render.py")
INSTALL_TIMEOUT_S = 1800  # a cold pip cache downloads bpy (hundreds of MB)
RENDER_TIMEOUT_S = 900  # a cold Warp kernel cache compiles every module once


def _bpy_requirement() -> str:
    """The dev extra's pinned bpy, so that this test and the others use one Blender."""
    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
    dev = pyproject["project"]["optional-dependencies"]["dev"]
    return next(d for d in dev if d.startswith("bpy=="))


def _run(argv: list, timeout: float, **kwargs) -> subprocess.CompletedProcess:
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=timeout, **kwargs)
    assert proc.returncode == 0, (argv, proc.stdout[-3000:], proc.stderr[-3000:])
    return proc


@pytest.fixture(scope="module")
def platform_zips(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """`scenesort addon-zip --platform all`: one zip per platform, sizes printed."""
    out = tmp_path_factory.mktemp("zips")
    argv = [sys.executable, "-m", "scenesort.backend.commands", "addon-zip", "--platform", "all",
            "-o", out]
    lines = _run(argv, INSTALL_TIMEOUT_S, cwd=REPO).stdout.strip().splitlines()
    zips = {}
    for line in lines:
        path, size = line.split("\t")
        assert size.endswith(f"({Path(path).stat().st_size:,} bytes)")
        zips[re.search(r"-(\w+-\w+)\.zip$", path).group(1)] = Path(path)
    assert set(zips) == {"linux-x64", "windows-x64", "macos-arm64"}
    return zips


@pytest.fixture(scope="module")
def extension_zip(platform_zips: dict[str, Path]) -> Path:
    return platform_zips["linux-x64"]


@pytest.mark.parametrize("name", ["linux-x64", "windows-x64", "macos-arm64"])
def test_blenders_validator_accepts_each_platform_zip(platform_zips, name: str) -> None:
    _run([sys.executable, BLENDER_EXT, "validate", platform_zips[name]], 120)
    with zipfile.ZipFile(platform_zips[name]) as zf:
        manifest = tomllib.loads(zf.read("blender_manifest.toml").decode())
        wheels = [n for n in zf.namelist() if n.startswith("wheels/")]
    assert manifest["platforms"] == [name]
    # The validator reads only the manifest: that every listed wheel is there is checked here.
    assert {w.removeprefix("./") for w in manifest["wheels"]} == set(wheels)
    tag = {"linux-x64": "manylinux", "windows-x64": "win_amd64", "macos-arm64": "arm64"}[name]
    assert all(w.endswith("-any.whl") or tag in w for w in wheels)  # no other platform's


@pytest.fixture(scope="module")
def bpy_only_python(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A new venv with `bpy` installed from the package index (via pip's cache)."""
    venv = tmp_path_factory.mktemp("venv") / "bpy-only"
    _run([sys.executable, "-m", "venv", str(venv)], 300)
    python = venv / "bin" / "python"
    _run([python, "-m", "pip", "install", "--quiet", _bpy_requirement()], INSTALL_TIMEOUT_S)
    code = (
        "import importlib.util as u; print([m for m in ('warp', 'fastapi', 'uvicorn', "
        "'pydantic', 'kernels', 'backend', 'scenesort') if u.find_spec(m)])"
    )
    assert _run([python, "-I", "-c", code], 120).stdout.strip() == "[]"
    return python


def test_manifest_lists_the_platform_and_every_wheel(extension_zip: Path) -> None:
    with zipfile.ZipFile(extension_zip) as zf:
        manifest = tomllib.loads(zf.read("blender_manifest.toml").decode())
        wheels = {n for n in zf.namelist() if n.startswith("wheels/")}
    assert manifest["platforms"] == ["linux-x64"]
    names = {re.split(r"-\d", Path(w).name, maxsplit=1)[0].lower() for w in wheels}
    assert {"scenesort", "warp_lang", "fastapi", "uvicorn", "pydantic_core"} <= names
    assert "numpy" not in names  # Blender ships it
    (engine,) = [w for w in wheels if Path(w).name.startswith("scenesort-")]
    with zipfile.ZipFile(extension_zip) as zf, zf.open(engine) as raw, \
            zipfile.ZipFile(raw) as wheel:
        tools = [n for n in wheel.namelist() if n.startswith("scenesort/backend/tools/")]
    assert not tools  # a packager's tools (addon-zip, bench, peers): not for Blender
    # Compiled packages come for Blender 4.2-5.0's Python 3.11 and 5.1+'s 3.13.
    core = sorted(w for w in wheels if "pydantic_core" in w)
    assert [re.search(r"-(cp3\d+)-", w).group(1) for w in core] == ["cp311", "cp313"]


def test_bundled_wheels_accept_blenders_numpy(extension_zip: Path) -> None:
    """Blender 4.2-5.0 ship numpy 1.26.4; no bundled package may ask for another one."""
    from packaging.requirements import Requirement

    asked = {}
    with zipfile.ZipFile(extension_zip) as outer:
        for name in (n for n in outer.namelist() if n.endswith(".whl")):
            with outer.open(name) as raw, zipfile.ZipFile(raw) as wheel:
                meta = next(n for n in wheel.namelist() if n.endswith(".dist-info/METADATA"))
                for line in wheel.read(meta).decode().splitlines():
                    if line.startswith("Requires-Dist: numpy"):
                        req = Requirement(line.removeprefix("Requires-Dist: "))
                        if req.marker is None or req.marker.evaluate({"extra": ""}):
                            asked[Path(name).name] = req.specifier
    assert any(n.startswith("warp_lang") for n in asked)  # the check saw the engine's users
    refused = {n: str(s) for n, s in asked.items() if not s.contains("1.26.4")}
    assert not refused


def test_install_from_zip_then_render_with_no_other_step(
    extension_zip: Path, bpy_only_python: Path, tmp_path: Path
) -> None:
    user = tmp_path / "blender-user"
    env = {
        "PATH": os.pathsep.join(["/usr/bin", "/bin"]),  # no venv, no `scenesort`
        "HOME": os.environ.get("HOME", str(tmp_path)),
        "BLENDER_USER_CONFIG": str(user / "config"),
        "BLENDER_USER_SCRIPTS": str(user / "scripts"),
        "BLENDER_USER_DATAFILES": str(user / "datafiles"),
        "BLENDER_USER_EXTENSIONS": str(user / "extensions"),
    }
    if "WARP_CACHE_PATH" in os.environ:  # CI keeps Warp's kernel cache in the clone
        env["WARP_CACHE_PATH"] = os.environ["WARP_CACHE_PATH"]
    argv = [bpy_only_python, "-I", SCRIPT, extension_zip, tmp_path]
    _run(argv, RENDER_TIMEOUT_S, cwd=tmp_path, env=env)
    info = json.loads((tmp_path / "render.json").read_text())
    site = user / "extensions" / ".local" / "lib" / "python3.11" / "site-packages"
    assert Path(info["site_packages"]) == site  # the engine came from the zip's wheel
    assert info["argv"][:4] == [str(bpy_only_python), "-s", "-m", "scenesort.backend.commands"]
    assert info["service_exit"] is not None  # disabling the add-on stopped it

    from scenesort.kernels import Camera

    from scenesort import kernels

    data = np.load(tmp_path / "render.npz")
    s = info["settings"]
    bvh = kernels.build_bvh(
        data["vertices"], data["indices"], method=s["method"], leaf_size=s["leaf_size"]
    )
    origins, directions, _, _ = Camera.from_dict(info["camera"]).rays()
    direct = kernels.render_ao(
        bvh, origins, directions, spp=s["spp"], distance=s["distance"], seed=s["seed"]
    )
    hit = direct.spp_used > 0  # the image is 0 with alpha 0 where the camera ray missed
    np.testing.assert_array_equal(data["ao"], np.where(hit, direct.ao, 0.0).astype(np.float32))
    np.testing.assert_array_equal(data["alpha"], hit.astype(np.float32))
    assert hit.mean() > 0.3 and data["ao"][hit].std() > 0.05  # a shaded floor
