"""`scenesort addon-zip`: build the installable Blender extension zip(s) from addon/.

With `--platform` each zip is self-contained and made for one Blender Python: the
add-on, a wheel of scenesort built at zip time (the engine and the service, without these
packaging tools) and the unmodified wheels of every runtime dependency Blender does not
ship, for Python 3.11 (Blender 4.2-5.0) or 3.13 (5.1 and later), listed under `wheels`
with the manifest's `platforms` and the Blender versions of that Python
(`blender_version_min`/`_max`), so that no Blender installs wheels it cannot load.
Blender unpacks them into its extensions' site-packages when it installs the zip.
Without `--platform` the zip holds the add-on alone (for a service of your own install).

The zip holds the extension's files at its root (blender_manifest.toml beside
__init__.py), as `blender --command extension build` lays it out. Entries carry a
fixed timestamp so that the same inputs give the same bytes. Wheels come from the
package index (`pip download --only-binary=:all: --no-deps`) and are cached, with
the resolved dependency closure, under `.cache/addon-wheels/`: a rebuild downloads
nothing.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import re
import subprocess
import sys
import tempfile
import tomllib
import zipfile
from pathlib import Path

from scenesort.backend.tools import addon_options

ROOT = Path(__file__).resolve().parents[2]
ADDON_DIR = ROOT / "addon"
CACHE_DIR = ROOT / ".cache" / "addon-wheels"
MANIFEST = "blender_manifest.toml"
INCLUDE_SUFFIXES = {".py", ".toml"}
FIXED_DATE = (2024, 1, 1, 0, 0, 0)  # zip timestamps cannot predate 1980; any fixed value works

# Blender's platform names -> the wheel platform tags pip may pick for them. Blender 4.2+
# needs glibc 2.28 on Linux and macOS 11 on Apple silicon; pip does not widen an explicit
# manylinux tag to older glibc versions, so they are listed. The denoiser's macOS wheel
# needs macOS 12: on macOS 11 Denoise cannot load it (the rest works).
PLATFORMS: dict[str, list[str]] = {
    "linux-x64": [f"manylinux_2_{m}_x86_64" for m in range(28, 16, -1)]
    + ["manylinux2014_x86_64", "manylinux2010_x86_64", "manylinux1_x86_64"],
    "windows-x64": ["win_amd64"],
    "macos-arm64": ["macosx_12_0_arm64", "macosx_11_0_arm64"],  # 12.0: pyoidn's wheel
}
# Blender platforms no zip can serve, and why (measured with `pip download --platform`).
NO_ZIP: dict[str, str] = {
    "macos-x64": "Warp publishes no macOS x86_64 wheel after 1.9.1 (its platform page lists "
    "Intel Macs as discontinued), and the engine needs Warp 1.19; on an Intel Mac, use a "
    "scenesort service on another computer (the Service URL and Allow a remote service "
    "preferences)",
}
# Blender's Python -> the Blender versions that run it, as the manifest's
# blender_version_min and blender_version_max (exclusive; None: no upper end).
BLENDER_RANGES: dict[str, tuple[str, str | None]] = {
    "3.11": ("4.2.0", "5.1.0"),
    "3.13": ("5.1.0", None),
}
PYTHON_VERSIONS = tuple(BLENDER_RANGES)
# The marker environment of each platform: pip evaluates dependency markers for the
# machine it runs on, so the closure is checked against the target's afterwards.
MARKER_ENV: dict[str, dict[str, str]] = {
    "linux-x64": {"sys_platform": "linux", "platform_system": "Linux", "os_name": "posix",
                  "platform_machine": "x86_64"},
    "windows-x64": {"sys_platform": "win32", "platform_system": "Windows", "os_name": "nt",
                    "platform_machine": "AMD64"},
    "macos-arm64": {"sys_platform": "darwin", "platform_system": "Darwin", "os_name": "posix",
                    "platform_machine": "arm64"},
}  # fmt: skip
# Blender bundles numpy: it is never put in the zip. The 3.11 closure is resolved against
# numpy 1.26.4 (the bpy 5.0 wheel requires numpy>=1.26,<2), the 3.13 one against numpy 2
# (bpy 5.1+ require numpy>=2.2): every bundled wheel then accepts Blender's numpy.
BLENDER_SHIPS = {"numpy"}
# This package (addon-zip, bench and the peer tracers) in the scenesort wheel: only a packager
# runs it, so the wheel bundled for Blender leaves it out.
TOOLS_IN_WHEEL = "scenesort/backend/tools/"
# Extras a Blender user could not pip-install, so the zip carries them: the denoiser (pyoidn,
# Intel Open Image Denoise with its CPU and CUDA devices) behind the Denoise checkbox.
BUNDLED_EXTRAS = ("denoise",)
BLENDER_NUMPY = {"3.11": "numpy==1.26.4", "3.13": "numpy>=2.2,<3"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `scenesort addon-zip`."""
    parser.add_argument(
        "--platform",
        choices=[*PLATFORMS, *NO_ZIP, "all"],
        default=None,
        help="bundle the engine and its wheels for this Blender platform ('all': one zip "
        "each); without it the zip holds the add-on alone",
    )
    parser.add_argument(
        "--python",
        choices=[*PYTHON_VERSIONS, "all"],
        default="all",
        help="the Blender Python to bundle for: 3.11 (Blender 4.2-5.0), 3.13 (5.1 and later); "
        "'all' (default): one zip each",
    )
    parser.add_argument(
        "--output",
        "-o",
        type=Path,
        default=None,
        help="zip file to write, or the folder when several are built "
        "(default: build/scenesort-<version>[-<platform>-<cpXY>].zip)",
    )
    parser.add_argument(
        "--source", type=Path, default=ADDON_DIR, help="the add-on folder (default: addon/)"
    )
    parser.add_argument(
        "--cache",
        type=Path,
        default=CACHE_DIR,
        help="where downloaded wheels are kept (default: .cache/addon-wheels/)",
    )


def addon_files(source: Path) -> list[Path]:
    """The files that ship: sources and the manifest, no caches or editor leftovers."""
    return [
        p
        for p in sorted(source.rglob("*"))
        if p.is_file()
        and p.suffix in INCLUDE_SUFFIXES
        and "__pycache__" not in p.parts
        and not any(part.startswith(".") for part in p.relative_to(source).parts)
    ]


def read_manifest(source: Path) -> tuple[str, dict]:
    """The manifest's text and its parsed form; ValueError if `source` has none."""
    path = source / MANIFEST
    if not path.is_file():
        raise ValueError(f"{source} has no {MANIFEST}: is it the add-on folder?")
    text = path.read_text(encoding="utf-8")
    return text, tomllib.loads(text)


def manifest_with_wheels(text: str, platform: str, python: str, wheels: list[str]) -> str:
    """The manifest with `platforms`, `wheels` and the Blender versions that run `python`
    (replacing the source's `blender_version_min`/`_max`) as top-level keys, before the
    first table, where TOML would otherwise put them inside it."""
    low, high = BLENDER_RANGES[python]
    versions = f'blender_version_min = "{low}"\n'
    if high is not None:
        versions += f'blender_version_max = "{high}"\n'
    lines = [
        versions if line.startswith("blender_version_min") else line
        for line in text.splitlines(keepends=True)
        if not line.startswith("blender_version_max")
    ]
    first_table = next((i for i, line in enumerate(lines) if line.startswith("[")), len(lines))
    entries = "".join(f'  "./wheels/{name}",\n' for name in wheels)
    added = f'platforms = ["{platform}"]\nwheels = [\n{entries}]\n\n'
    return "".join(lines[:first_table]) + added + "".join(lines[first_table:])


def runtime_requirements(pyproject: Path) -> list[str]:
    """pyproject's pinned runtime dependencies and bundled extras, less what Blender ships."""
    project = tomllib.loads(pyproject.read_text(encoding="utf-8"))["project"]
    deps = project["dependencies"]
    for extra in BUNDLED_EXTRAS:
        deps = [*deps, *project["optional-dependencies"][extra]]
    return [d for d in deps if re.split(r"[<>=!~\[; ]", d, maxsplit=1)[0] not in BLENDER_SHIPS]


def _target_options(platform: str, python: str) -> list[str]:
    """pip's options selecting CPython `python` wheels for a Blender platform."""
    abi = "cp" + python.replace(".", "")
    options = ["--only-binary=:all:", "--python-version", python]
    options += ["--implementation", "cp", "--abi", abi, "--abi", "abi3", "--abi", "none"]
    for tag in PLATFORMS[platform]:
        options += ["--platform", tag]
    return options


def _pip(args: list[str], what: str) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "pip", "--disable-pip-version-check", *args],
        capture_output=True,
        text=True,
    )
    if proc.returncode != 0:
        tail = "\n".join((proc.stderr or proc.stdout).strip().splitlines()[-8:])
        raise ValueError(f"pip could not {what}:\n{tail}")


def resolve(platform: str, python: str, requirements: list[str], cache: Path) -> list[str]:
    """Wheel file names of the dependency closure of `requirements` (numpy left out),
    as pip resolves it for this platform and Python; cached by its inputs."""
    pins = [*requirements, BLENDER_NUMPY[python]]
    options = _target_options(platform, python)
    key = hashlib.sha256(json.dumps([pins, options]).encode()).hexdigest()[:16]
    cached = cache / "resolved" / f"{platform}-py{python}-{key}.json"
    if cached.is_file():
        return json.loads(cached.read_text())
    with tempfile.TemporaryDirectory() as tmp:
        report = Path(tmp) / "report.json"
        _pip(
            ["install", "--dry-run", "--ignore-installed", "--quiet", "--report", str(report),
             "--target", str(Path(tmp) / "t"), *options, *pins],
            f"resolve the dependencies for {platform}, Python {python}",
        )  # fmt: skip
        installs = json.loads(report.read_text())["install"]
    check_markers(installs, platform, python)
    names = sorted(
        item["download_info"]["url"].rsplit("/", 1)[-1]
        for item in installs
        if item["metadata"]["name"].lower() not in BLENDER_SHIPS
    )
    cached.parent.mkdir(parents=True, exist_ok=True)
    cached.write_text(json.dumps(names, indent=1))
    return names


def check_markers(installs: list[dict], platform: str, python: str) -> None:
    """ValueError if a package of the closure needs, on the target platform and Python,
    a dependency that pip (which evaluates markers for this machine) left out."""
    from packaging.markers import Marker
    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name

    env = {**MARKER_ENV[platform], "python_version": python, "python_full_version": python + ".0",
           "implementation_name": "cpython", "platform_python_implementation": "CPython",
           "extra": ""}  # fmt: skip
    closure = {canonicalize_name(item["metadata"]["name"]) for item in installs}
    for item in installs:
        for text in item["metadata"].get("requires_dist") or []:
            req = Requirement(text)
            if req.marker is None or not Marker(str(req.marker)).evaluate(env):
                continue
            if canonicalize_name(req.name) not in closure:
                raise ValueError(
                    f"{item['metadata']['name']} needs {req} on {platform} (Python {python}), "
                    "which pip left out when resolving on this machine: add it to the project's "
                    "dependencies with that marker"
                )


def _pin_of(wheel_name: str) -> str:
    """`name==version` of a wheel file name (PEP 427: name-version-...)."""
    name, version = wheel_name.split("-")[:2]
    return f"{name}=={version}"


def fetch_wheels(platform: str, python: str, names: list[str], cache: Path) -> list[Path]:
    """The wheels `names` from the cache, downloading only the missing ones."""
    missing = [n for n in names if not (cache / n).is_file()]
    if missing:
        _pip(
            ["download", "--no-deps", "--quiet", "--dest", str(cache),
             *_target_options(platform, python), *map(_pin_of, missing)],
            f"download {len(missing)} wheels for {platform}, Python {python}",
        )  # fmt: skip
    absent = [n for n in names if not (cache / n).is_file()]
    if absent:
        raise ValueError(f"pip did not download {', '.join(absent)} for {platform}")
    return [cache / n for n in names]


def engine_wheel(project: Path, out_dir: Path) -> Path:
    """A wheel of scenesort (kernels + backend) built from the checkout, without deps, and
    without the packaging tools (`without_tools`): what Blender installs."""
    _pip(
        ["wheel", "--no-deps", "--quiet", "--wheel-dir", str(out_dir), str(project)],
        "build the scenesort wheel",
    )
    wheels = sorted(out_dir.glob("scenesort-*.whl"))
    if len(wheels) != 1:
        raise ValueError(f"building the scenesort wheel gave {len(wheels)} wheels in {out_dir}")
    return without_tools(wheels[0])


def without_tools(wheel: Path) -> Path:
    """Rewrite `wheel` in place without the package of these tools (TOOLS_IN_WHEEL): its
    files and their lines in RECORD go, every other entry is copied as it was."""
    prefix = TOOLS_IN_WHEEL.encode()
    rewritten = wheel.with_name(wheel.name + ".part")
    with zipfile.ZipFile(wheel) as source, zipfile.ZipFile(rewritten, "w") as target:
        for info in source.infolist():
            if info.filename.startswith(TOOLS_IN_WHEEL):
                continue
            data = source.read(info)
            if info.filename.endswith(".dist-info/RECORD"):  # lines: path,hash,size
                lines = data.splitlines(keepends=True)
                data = b"".join(line for line in lines if not line.startswith(prefix))
            target.writestr(info, data)
    rewritten.replace(wheel)
    return wheel


def platform_wheels(platform: str, python: str, project: Path, cache: Path) -> list[Path]:
    """Every dependency wheel for one platform and Blender Python."""
    requirements = runtime_requirements(project / "pyproject.toml")
    names = resolve(platform, python, requirements, cache)
    return sorted(fetch_wheels(platform, python, names, cache))


def zip_name(manifest: dict, platform: str | None = None, python: str | None = None) -> str:
    """`scenesort-<version>.zip`, or `scenesort-<version>-<platform>-cp<XY>.zip`."""
    suffix = f"-{platform}-cp{python.replace('.', '')}" if platform else ""
    return f"{manifest['id']}-{manifest['version']}{suffix}.zip"


def _write(zf: zipfile.ZipFile, name: str, data: bytes, compress: int) -> None:
    info = zipfile.ZipInfo(name, FIXED_DATE)
    info.compress_type = compress
    info.external_attr = 0o644 << 16
    zf.writestr(info, data)


def build_zip(
    source: Path,
    output: Path | None = None,
    platform: str | None = None,
    wheels: list[Path] = (),
    python: str | None = None,
) -> Path:
    """Write one zip and return its path; ValueError if `source` is not an extension, or
    if its copy of the AO settings differs from the engine's (tools/addon_options.py)."""
    text, manifest = read_manifest(source)
    if addon_options.stale(source / "ao_options.py"):
        raise ValueError(f"{source / 'ao_options.py'} differs from the engine's AO settings "
                         "(scenesort/ao_options.py): run `scenesort addon-options` first")
    if output is None:
        output = Path("build") / zip_name(manifest, platform, python)
    if platform:
        text = manifest_with_wheels(text, platform, python, [w.name for w in wheels])
    output.parent.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(output, "w") as zf:
        for path in addon_files(source):
            data = text.encode() if path.name == MANIFEST else path.read_bytes()
            _write(zf, path.relative_to(source).as_posix(), data, zipfile.ZIP_DEFLATED)
        for wheel in wheels:  # already compressed: stored as they are
            _write(zf, f"wheels/{wheel.name}", wheel.read_bytes(), zipfile.ZIP_STORED)
    return output


def build_platform_zips(
    source: Path, platforms: list[str], pythons: list[str], output: Path | None, cache: Path
) -> list[Path]:
    """One self-contained zip per platform and Blender Python, sharing one freshly built
    engine wheel; `output` is the zip when there is one, else their folder."""
    project = source.resolve().parent
    _, manifest = read_manifest(source)
    if not (project / "pyproject.toml").is_file():
        raise ValueError(f"{project} has no pyproject.toml: run from a scenesort checkout")
    pyproject = tomllib.loads((project / "pyproject.toml").read_text(encoding="utf-8"))
    engine_version = pyproject["project"]["version"]
    if manifest["version"] != engine_version:
        raise ValueError(
            f"the add-on is version {manifest['version']} ({MANIFEST}) but the engine "
            f"{engine_version} (pyproject.toml): the add-on refuses a service of another "
            "version, so set both to the same"
        )
    zips = []
    with tempfile.TemporaryDirectory() as tmp:
        engine = engine_wheel(project, Path(tmp))
        for platform in platforms:
            for python in pythons:
                wheels = [engine, *platform_wheels(platform, python, project, cache)]
                target = output
                if output is not None and len(platforms) * len(pythons) > 1:
                    target = output / zip_name(manifest, platform, python)
                zips.append(build_zip(source, target, platform, wheels, python))
    return zips


def run(args: argparse.Namespace) -> int:
    if args.platform in NO_ZIP:
        print(f"scenesort addon-zip: no {args.platform} zip: {NO_ZIP[args.platform]}",
              file=sys.stderr)  # fmt: skip
        return 2
    try:
        if args.platform is None:
            zips = [build_zip(args.source, args.output)]
        else:
            platforms = list(PLATFORMS) if args.platform == "all" else [args.platform]
            pythons = list(PYTHON_VERSIONS) if args.python == "all" else [args.python]
            zips = build_platform_zips(args.source, platforms, pythons, args.output, args.cache)
    except (ValueError, OSError, KeyError, tomllib.TOMLDecodeError) as exc:
        print(f"scenesort addon-zip: {exc}", file=sys.stderr)
        return 1
    for path in zips:
        size = path.stat().st_size
        print(f"{path}\t{size / 1e6:.1f} MB ({size:,} bytes)")
    return 0
