"""The engine on numpy 2, as Blender 5.1 and later ship it: engine_digests.py's answers
(BVH trees, traces, DACRT, AO at fixed samples and to an error target, a two-level scene)
equal this environment's (numpy 1.26, Blender 4.2-5.0's) bit for bit.

The numpy-2 Python is $SCENESORT_NUMPY2_PYTHON: `.ci/run` makes it (.venv-numpy2, Python
3.13 with this project) and also runs the kernels' and stability suites in it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).with_name("engine_digests.py")


def _digests(python: str) -> dict[str, str]:
    proc = subprocess.run([python, SCRIPT], capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_numpy_2_gives_numpy_1s_answers_bit_for_bit() -> None:
    numpy2 = os.environ.get("SCENESORT_NUMPY2_PYTHON")
    if np.__version__.startswith("2."):
        pytest.skip("this is the numpy 2 environment: the numpy 1 run compares the two")
    if not numpy2:
        pytest.skip("set SCENESORT_NUMPY2_PYTHON to a Python with numpy 2 and this project "
                    "(.ci/run makes .venv-numpy2)")  # fmt: skip
    here, there = _digests(sys.executable), _digests(numpy2)
    assert here.pop("numpy").startswith("1.") and there.pop("numpy").startswith("2.")
    assert len(here) == 11 and there == here
