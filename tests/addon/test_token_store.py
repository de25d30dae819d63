"""The token of a service of your own: in a file only the user can read (the engine's
token_file functions), never in Blender's preferences file, and back in a new session."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
from pathlib import Path

import bpy
from blender_scenes import REPO

TOKEN = "tok-5e1f0c9a7b3d42e8"  # nowhere else in any file Blender writes
URL = "http://127.0.0.1:8779-marker"


def _run(code: str, env: dict) -> str:
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    return proc.stdout.strip().splitlines()[-1]


def test_the_token_stays_out_of_userpref_and_comes_back(tmp_path: Path) -> None:
    env = {**os.environ, **{f"BLENDER_USER_{d.upper()}": str(tmp_path / d)
                            for d in ("config", "scripts", "datafiles", "extensions")}}  # fmt: skip
    start = ("import json, bpy, addon; bpy.ops.wm.read_userpref(); addon.register();"
             "p = bpy.context.preferences.addons['addon'].preferences;")
    _run(start + f"p.server_url, p.server_token = {URL!r}, {TOKEN!r};"
         "bpy.ops.wm.save_userpref(); print('saved')", env)  # fmt: skip
    userpref = (tmp_path / "config" / "userpref.blend").read_bytes()
    assert userpref.startswith(b"BLENDER")  # uncompressed: a search of its bytes means something
    assert URL.encode() in userpref  # the other preferences are in it...
    assert TOKEN.encode() not in userpref  # ...the token is not
    path = tmp_path / "config" / "scenesort" / "service-token"
    assert path.read_text().strip() == TOKEN
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert stat.S_IMODE(path.parent.stat().st_mode) == 0o700
    read = "print(json.dumps([p.server_url, p.server_token]))"
    assert json.loads(_run(start + read, env)) == [URL, TOKEN]  # a new session
    assert json.loads(_run(start + "p.server_token = '';" + read, env)) == [URL, ""]
    assert not path.exists()  # cleared: the file goes


def test_a_token_file_others_can_read_is_not_used(registered) -> None:
    """A file with looser permissions may have leaked: the preference reads as empty."""
    from addon import prefs

    p = bpy.context.preferences.addons["addon"].preferences
    p.server_token = TOKEN
    path = prefs.token_path()
    assert p.server_token == TOKEN and path.is_file()
    os.chmod(path, 0o644)
    try:
        prefs._session_token = ""  # a new session: only the file could give it back
        assert p.server_token == ""
    finally:
        p.server_token = ""
    assert not path.exists()
