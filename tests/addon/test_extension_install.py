"""From a fresh Blender user directory, in each Blender Python: install the linux-x64 zip
made for that Python, render a frame, an animation and Cycles' AO pass.

A throw-away Python environment with only `bpy` (and what bpy itself needs: numpy, as
Blender ships it) runs tests/addon/install_and_render.py: Blender's own installer puts the
zip's wheels into the extensions' site-packages, and the add-on, with no setting changed,
no SCENESORT_COMMAND and no `scenesort` on PATH, starts the service with that Python and
renders (Render AO, F12, Ctrl-F12). The image must equal a direct engine call made here,
and a render at 256 samples must match that Blender's own Cycles AO pass as
tests/addon/test_shading.py's parity test does. This
runs for Blender 4.2 and 4.5 LTS (their newest patches), 5.0 (the test extra's bpy) and the
newest 5.x on Python 3.13 with numpy 2; in each, every RNA property the add-on names must exist, or
have a fallback (tests/addon/rna_audit.py).

The bpy environments are kept in $SCENESORT_BPY_VENVS when it is set (CI: under .cache/),
else made in a temporary folder; Python 3.13 is $SCENESORT_PYTHON313 or `python3.13`.
"""

from __future__ import annotations

import json
import os
import platform
import re
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import numpy as np
import pytest
from blender_scenes import BLENDER_EXT, REPO
from packaging.markers import Marker
from packaging.requirements import Requirement
from scenesort.backend.tools import addon_zip

pytestmark = [
    pytest.mark.skipif(
        not (sys.platform.startswith("linux") and platform.machine() == "x86_64"),
        reason="installs the linux-x64 zip, which only this platform can run",
    ),
    pytest.mark.slow,  # builds six zips and up to three bpy venvs: minutes when cold
]
SCRIPT = Path(__file__).with_name("install_and_render.py")
AUDIT = Path(__file__).with_name("rna_audit.py")
WIDTH, HEIGHT = 32, 24  # install_and_render.py's image
INSTALL_TIMEOUT_S = 1800  # a cold pip cache downloads bpy (hundreds of MB)
RENDER_TIMEOUT_S = 900  # a cold Warp kernel cache compiles every module once
PLATFORMS = ["linux-x64", "windows-x64", "macos-arm64"]
# Blender -> (its Python, the numpy Blender ships with it, as the venv gets it). 4.2.23 and
# 4.5.15 are the newest 4.2 and 4.5 LTS patches on the index; 5.3.0 the newest 5.x. None:
# the test extra's bpy.
BLENDERS = {
    "4.2.23": ("3.11", "numpy==1.26.4"),
    "4.5.15": ("3.11", "numpy==1.26.4"),
    "dev": ("3.11", None),
    "5.3.0": ("3.13", "numpy>=2.2,<3"),
}
# Properties that a Blender may lack, and where the add-on reads them from then.
FALLBACKS = {
    ("Object", "shadow_terminator_geometry_offset"): "Object.cycles (Blender 4.2), else 0.1",
}


def _bpy_requirement() -> str:
    """The test extra's pinned bpy for Python 3.11, so that this test and the others use
    one Blender."""
    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
    for line in pyproject["project"]["optional-dependencies"]["test"]:
        req = Requirement(line)
        if req.name == "bpy" and req.marker.evaluate({"python_version": "3.11"}):
            return f"bpy{req.specifier}"
    raise AssertionError("the test extra pins no bpy for Python 3.11")


def _run(argv: list, timeout: float, **kwargs) -> subprocess.CompletedProcess:
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=timeout, **kwargs)
    assert proc.returncode == 0, (argv, proc.stdout[-3000:], proc.stderr[-3000:])
    return proc


def _base_python(version: str) -> str | None:
    """An interpreter of `version` to make the venv with; None if this machine has none."""
    if version == f"{sys.version_info.major}.{sys.version_info.minor}":
        return sys.executable
    candidates = [os.environ.get(f"SCENESORT_PYTHON{version.replace('.', '')}", ""),
                  shutil.which(f"python{version}") or ""]  # fmt: skip
    for exe in filter(None, candidates):
        probe = subprocess.run([exe, "-c", "import sys; print(sys.version[:4])"],
                               capture_output=True, text=True, timeout=60)  # fmt: skip
        if probe.returncode == 0 and probe.stdout.strip() == version:
            return exe
    return None


@pytest.fixture(scope="module")
def platform_zips(tmp_path_factory: pytest.TempPathFactory) -> dict[tuple[str, str], Path]:
    """`scenesort addon-zip --platform all`: one zip per platform and Blender Python."""
    out = tmp_path_factory.mktemp("zips")
    argv = [sys.executable, "-m", "scenesort.backend.commands", "addon-zip", "--platform", "all",
            "-o", out]
    lines = _run(argv, INSTALL_TIMEOUT_S, cwd=REPO).stdout.strip().splitlines()
    zips = {}
    for line in lines:
        path, size = line.split("\t")
        assert size.endswith(f"({Path(path).stat().st_size:,} bytes)")
        name, tag = re.search(r"-(\w+-\w+)-cp3(\d+)\.zip$", path).groups()
        zips[name, f"3.{tag}"] = Path(path)
    assert set(zips) == {(p, py) for p in PLATFORMS for py in ("3.11", "3.13")}
    return zips


def _manifest_and_wheels(path: Path) -> tuple[dict, list[str]]:
    with zipfile.ZipFile(path) as zf:
        manifest = tomllib.loads(zf.read("blender_manifest.toml").decode())
        return manifest, [n for n in zf.namelist() if n.startswith("wheels/")]


@pytest.mark.parametrize("python", ["3.11", "3.13"])
@pytest.mark.parametrize("name", PLATFORMS)
def test_blenders_validator_accepts_each_zip(platform_zips, name: str, python: str) -> None:
    _run([sys.executable, BLENDER_EXT, "validate", platform_zips[name, python]], 120)
    manifest, wheels = _manifest_and_wheels(platform_zips[name, python])
    assert manifest["platforms"] == [name]
    # The validator reads only the manifest: that every listed wheel is there is checked here.
    assert {w.removeprefix("./") for w in manifest["wheels"]} == set(wheels)
    tag = {"linux-x64": "manylinux", "windows-x64": "win_amd64", "macos-arm64": "arm64"}[name]
    assert all(w.endswith("-any.whl") or tag in w for w in wheels)  # no other platform's


@pytest.mark.parametrize("python", ["3.11", "3.13"])
@pytest.mark.parametrize("name", PLATFORMS)
def test_each_zip_carries_one_pythons_wheels_for_the_blenders_that_run_it(
    platform_zips, name: str, python: str
) -> None:
    """Blender 4.2.0's installer ignores wheels' Python tags: a zip must not offer it any
    other Python's build. blender_version_max is exclusive: 5.1 takes the cp313 zip."""
    manifest, wheels = _manifest_and_wheels(platform_zips[name, python])
    expected = {"3.11": ("4.2.0", "5.1.0"), "3.13": ("5.1.0", None)}[python]
    assert (manifest["blender_version_min"], manifest.get("blender_version_max")) == expected
    cp = "cp" + python.replace(".", "")
    pythons = {w.rsplit("-", 3)[1] for w in wheels}  # PEP 427: ...-python-abi-platform.whl
    assert pythons <= {cp, "py3", "py2.py3"} and cp in pythons
    names = {re.split(r"-\d", Path(w).name, maxsplit=1)[0].lower() for w in wheels}
    assert {"scenesort", "warp_lang", "fastapi", "uvicorn", "pydantic_core", "pyoidn"} <= names
    assert "numpy" not in names  # Blender ships it
    assert len([w for w in wheels if "pydantic_core" in w]) == 1


@pytest.mark.parametrize(("python", "numpy"), [("3.11", "1.26.4"), ("3.13", "2.2.6"),
                                               ("3.13", "2.5.5")])  # fmt: skip
def test_bundled_wheels_accept_blenders_numpy(platform_zips, python: str, numpy: str) -> None:
    """Blender 4.2-5.0 ship numpy 1.26, 5.1+ numpy 2 (>= 2.2): no bundled package, the
    scenesort wheel among them, may ask that Python for another one."""
    env = {"python_version": python, "python_full_version": f"{python}.0", "extra": "",
           "sys_platform": "linux", "platform_system": "Linux", "platform_machine": "x86_64"}
    asked = {}
    with zipfile.ZipFile(platform_zips["linux-x64", python]) as outer:
        for name in (n for n in outer.namelist() if n.endswith(".whl")):
            with outer.open(name) as raw, zipfile.ZipFile(raw) as wheel:
                meta = next(n for n in wheel.namelist() if n.endswith(".dist-info/METADATA"))
                for line in wheel.read(meta).decode().splitlines():
                    if line.startswith("Requires-Dist: numpy"):
                        req = Requirement(line.removeprefix("Requires-Dist: "))
                        if req.marker is None or Marker(str(req.marker)).evaluate(env):
                            asked[Path(name).name] = req.specifier
    assert any(n.startswith("warp_lang") for n in asked)  # the check saw the engine's users
    assert any(n.startswith("scenesort-") for n in asked)  # and the engine's own wheel
    refused = {n: str(s) for n, s in asked.items() if not s.contains(numpy)}
    assert not refused


def test_the_bundled_engine_wheel_is_the_tools_free_one(platform_zips) -> None:
    with zipfile.ZipFile(platform_zips["linux-x64", "3.11"]) as zf:
        (engine,) = [w for w in zf.namelist() if Path(w).name.startswith("scenesort-")]
        with zf.open(engine) as raw, zipfile.ZipFile(raw) as wheel:
            tools = [n for n in wheel.namelist() if n.startswith(addon_zip.TOOLS_IN_WHEEL)]
    assert not tools  # a packager's tools (addon-zip, bench, peers): not for Blender


@pytest.fixture(scope="module", params=list(BLENDERS))
def blender(request: pytest.FixtureRequest, tmp_path_factory) -> tuple[str, Path]:
    """(Blender Python version, the python of a venv with only that `bpy`), made once per
    $SCENESORT_BPY_VENVS folder (pip's cache makes a new one cheap)."""
    version = request.param
    python, numpy = BLENDERS[version]
    base = _base_python(python)
    if base is None:
        pytest.skip(f"bpy {version} needs Python {python}: set SCENESORT_PYTHON"
                    f"{python.replace('.', '')} to one")  # fmt: skip
    requirements = [_bpy_requirement()] if numpy is None else [f"bpy=={version}", numpy]
    root = os.environ.get("SCENESORT_BPY_VENVS")
    folder = Path(root) if root else tmp_path_factory.mktemp("venv")
    venv = folder / ("bpy-" + "-".join(requirements)).translate(str.maketrans("=<>,", "____"))
    exe = venv / "bin" / "python"
    done = venv / "installed.txt"  # written last: a venv without it was interrupted
    if not done.is_file() or done.read_text() != "\n".join(requirements):
        shutil.rmtree(venv, ignore_errors=True)
        _run([base, "-m", "venv", str(venv)], 300)
        _run([exe, "-m", "pip", "install", "--quiet", *requirements], INSTALL_TIMEOUT_S)
        done.write_text("\n".join(requirements))
    code = (
        "import importlib.util as u; print([m for m in ('warp', 'fastapi', 'uvicorn', "
        "'pydantic', 'kernels', 'backend', 'scenesort') if u.find_spec(m)])"
    )
    assert _run([exe, "-I", "-c", code], 120).stdout.strip() == "[]"
    return python, exe


def test_every_rna_property_the_addon_names_exists(blender: tuple[str, Path]) -> None:
    """Each type's members that the add-on names here (bpy 5.0.1) exist in that Blender, or
    the add-on has a fallback for them."""
    from rna_audit import audit

    _, exe = blender
    here = audit(REPO / "addon")
    there = json.loads(_run([exe, "-I", AUDIT, REPO / "addon"], 300).stdout.splitlines()[-1])
    assert sum(map(len, here.values())) > 150  # the audit saw the add-on's reads
    missing = {(t, n) for t, names in here.items() for n in set(names) - set(there[t])}
    assert missing <= set(FALLBACKS), missing - set(FALLBACKS)


def test_install_from_zip_then_render_with_no_other_step(
    platform_zips, blender: tuple[str, Path], tmp_path: Path
) -> None:
    python, exe = blender
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
    _run([exe, "-I", SCRIPT, platform_zips["linux-x64", python], tmp_path], RENDER_TIMEOUT_S,
         cwd=tmp_path, env=env)  # fmt: skip
    info = json.loads((tmp_path / "render.json").read_text())
    site = user / "extensions" / ".local" / "lib" / f"python{python}" / "site-packages"
    assert Path(info["site_packages"]) == site  # the engine came from the zip's wheel
    assert info["argv"][:4] == [str(exe), "-s", "-m", "scenesort.backend.commands"]
    assert info["service_exit"] is not None  # disabling the add-on stopped it
    # The device probe ran with that Blender's Python and the zip's Warp: the service got
    # the first CUDA device it found, else the CPU.
    found = info["devices"]
    assert found[0] == "cpu" and all(d.startswith("cuda:") for d in found[1:])
    assert info["argv"][-2:] == ["--device", found[1] if len(found) > 1 else "cpu"]

    from scenesort.kernels import Camera

    from scenesort import kernels

    data = np.load(tmp_path / "render.npz")
    s = info["settings"]
    bvh = kernels.build_bvh(
        data["vertices"], data["indices"], method=s["method"], leaf_size=s["leaf_size"]
    )
    cam = Camera.from_dict(info["camera"])
    origins, directions, _, _ = cam.rays()
    # Through the scene's pixel filter (that Blender's Cycles' defaults)
    pixel_filter, filter_width = s["film"]
    direct = kernels.render_film(bvh, cam, spp=s["spp"], distance=s["distance"], seed=s["seed"],
                                 pixel_filter=pixel_filter, filter_width=filter_width)
    alpha = direct.alpha.ravel()
    hit = alpha > 0  # the image is 0 with alpha 0 where no sample hit
    # Bit for bit, also where that Blender's service ran the engine on numpy 2.
    np.testing.assert_array_equal(data["ao"], np.maximum(direct.ao.ravel() + alpha - 1.0, 0.0))
    np.testing.assert_array_equal(data["alpha"], alpha)
    assert hit.mean() > 0.3 and data["ao"][hit].std() > 0.05  # a shaded floor
    # F12 with the engine (Film > Transparent, a float EXR Blender wrote): the same image.
    np.testing.assert_array_equal(data["f12"][:, 0], data["ao"])
    np.testing.assert_array_equal(data["f12"][:, 3], data["alpha"])
    # Denoise works from the zip (its pyoidn wheel): the direct call's denoised image.
    # Denoising renders pixel centres (AoOptions.film_fallback)
    denoised = kernels.render_ao(bvh, origins, directions, spp=s["spp"], distance=s["distance"],
                                 seed=s["seed"], denoise=True, image_shape=(HEIGHT, WIDTH))
    centre = denoised.spp_used > 0
    np.testing.assert_allclose(data["denoised"][:, 0], np.where(centre, denoised.ao, 0.0),
                               atol=1e-5)  # fmt: skip
    assert np.abs(data["denoised"][centre, 0] - data["ao"][centre]).max() > 0.05  # denoised
    # Ctrl-F12 through that Blender's numbered output: frame 1 is F12's image, and the box
    # moved on frame 2.
    first, second = data["frames"]
    np.testing.assert_array_equal(first, data["f12"])
    assert np.abs(second[:, 0] - first[:, 0]).max() > 0.1
    # Parity with that Blender's Cycles AO pass (test_shading's test, at PARITY_SPP).
    from cycles_reference import clean_pixels, judge, read_cycles_ao

    cycles_a, alpha = read_cycles_ao(tmp_path / "cycles_11")
    cycles_b, _ = read_cycles_ao(tmp_path / "cycles_12")
    ours = data["parity"][:, 0].reshape(HEIGHT, WIDTH)
    clean = clean_pixels((alpha == 1.0) & (data["parity"][:, 3] == 1.0).reshape(HEIGHT, WIDTH))
    assert clean.sum() > 200
    cycles_rmse, _ = judge(cycles_b, cycles_a, clean)
    rmse, z = judge(ours, cycles_a, clean)
    assert rmse <= 1.25 * cycles_rmse and z < 4.0, (rmse, cycles_rmse, z)
