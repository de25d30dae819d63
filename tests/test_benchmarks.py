"""Every benchmark script starts: its imports resolve and its options parse (`--help`).
Benchmarks run by hand, not in CI, so a renamed module would otherwise go unnoticed until
someone needs the numbers (benchmarks/ao_error.py imported the options from their old
place for several changes)."""

from __future__ import annotations

import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = sorted(p for p in (ROOT / "benchmarks").glob("*.py")
                 if 'if __name__ == "__main__"' in p.read_text())


@pytest.mark.slow
def test_every_benchmark_script_starts():
    assert len(SCRIPTS) >= 20

    def run(script: Path) -> tuple[Path, subprocess.CompletedProcess]:
        return script, subprocess.run([sys.executable, str(script), "--help"], cwd=ROOT,
                                      capture_output=True, text=True, timeout=300)

    with ThreadPoolExecutor(4) as pool:
        failed = {script.name: done.stderr[-2000:]
                  for script, done in pool.map(run, SCRIPTS) if done.returncode != 0}
    assert not failed, failed
