"""`scenesort render-frames --ray` on a real local Ray cluster started here: the images equal
the one-process run bit for bit, a worker killed mid-frame is retried, a frame that keeps
failing is reported by number with the others written, --resume, what is sent per frame,
and the message naming the extra when Ray is missing."""

from __future__ import annotations

import os
import signal
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import ray
from bundles import look_at_camera
from scenesort.backend.commands import main
from scenesort.backend.render.bundle import BundleWriter
from scenesort.backend.render.cluster import render_frames_ray
from scenesort.backend.render.frames import frame_paths, render_frames

pytestmark = pytest.mark.slow  # a local Ray cluster: ~14 s


def grid(n: int, size: float, lift: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """An n x n grid of quads in z=0 bent up by `lift` * x^2."""
    xs = np.linspace(-size / 2, size / 2, n + 1, dtype=np.float32)
    gx, gy = np.meshgrid(xs, xs, indexing="xy")
    v = np.stack([gx.ravel(), gy.ravel(), lift * gx.ravel() ** 2], 1).astype(np.float32)
    i = np.arange(n * n)
    a = (i // n) * (n + 1) + i % n
    quads = np.stack([a, a + 1, a + n + 2, a + n + 1], 1)
    f = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    return v, f.astype(np.int32)


def at(x: float, y: float, z: float = 0.0) -> np.ndarray:
    m = np.zeros((3, 4), np.float32)
    m[:, :3] = np.eye(3)
    m[:, 3] = (x, y, z)
    return m


FLOOR, BLOB = grid(8, 8.0), grid(4, 1.5)
# Frame 3 brings a 180k-triangle mesh: its build keeps the frame's task running long enough
# (about a second) for a test to find its worker and kill it.
HEAVY = grid(300, 2.0, 0.3)
FRAMES = range(1, 7)
SLOW_FRAME = 3


def frame_scene(number: int) -> list:
    blob = grid(4, 1.5, 0.1 * number) if number >= 4 else BLOB  # deforms from frame 4 on
    scene = [(FLOOR, at(0, 0)), (BLOB, at(-1.5, 0.0, 0.2 * number)), (blob, at(1.5, 0.0))]
    return scene + ([(HEAVY, at(0.0, 1.5, 0.5))] if number == SLOW_FRAME else [])


@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory) -> Path:
    writer = BundleWriter()
    for number in FRAMES:
        writer.frame(number, look_at_camera((0.1 * number, 0.0, 6.0), 40, 30),
                     frame_scene(number))
    return writer.write(tmp_path_factory.mktemp("bundle"))


@pytest.fixture(scope="module")
def reference(bundle: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("one-process")
    render_frames(bundle, out, threads=1, progress=False)
    return out


@pytest.fixture(scope="module")
def cluster() -> Iterator[None]:
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False,
             logging_level="WARNING")
    yield
    ray.shutdown()


def same_frames(a: Path, b: Path, frames) -> None:
    for number in frames:
        for path_a, path_b in zip(frame_paths(a, number), frame_paths(b, number), strict=True):
            assert path_a.read_bytes() == path_b.read_bytes(), f"frame {number}: {path_b.name}"


class Killer(threading.Thread):
    """Kills (SIGKILL) every Ray worker seen running `frame N`'s task, up to `times`."""

    def __init__(self, frame: int, times: int) -> None:
        super().__init__(daemon=True)
        self.title, self.times, self.killed = f"ray::frame {frame}".encode(), times, 0
        self.stop = threading.Event()
        # A killed worker keeps its title until it has exited: kill each process once.
        self.seen: set[int] = set()

    def run(self) -> None:
        while not self.stop.wait(0.002) and self.killed < self.times:
            for entry in os.scandir("/proc"):
                if not entry.name.isdigit() or int(entry.name) in self.seen:
                    continue
                try:
                    with open(f"/proc/{entry.name}/cmdline", "rb") as f:
                        title = f.read().split(b"\0")[0]
                except OSError:
                    continue
                if title == self.title:
                    os.kill(int(entry.name), signal.SIGKILL)
                    self.seen.add(int(entry.name))
                    self.killed += 1
                    break


def test_cluster_frames_equal_one_process(cluster, bundle, reference, tmp_path) -> None:
    run = render_frames_ray(bundle, tmp_path, threads=1)
    assert run.written == list(FRAMES) and not run.failed and not run.skipped
    same_frames(reference, tmp_path, FRAMES)
    # After the first frame the driver sends a frame's view and instance list, plus the
    # meshes first seen in it: frame 2 moved only the camera and a transform.
    mesh_bytes = HEAVY[0].nbytes + HEAVY[1].nbytes
    assert run.sent_bytes[2] < 4096
    assert mesh_bytes <= run.sent_bytes[SLOW_FRAME] < mesh_bytes + 4096
    assert all(0 < run.sent_bytes[n] < 8192 for n in (4, 5, 6))  # a 50-triangle deformation


def test_resume_renders_only_missing_frames(cluster, bundle, reference, tmp_path) -> None:
    render_frames_ray(bundle, tmp_path, frames=[1, 2, 5])
    run = render_frames_ray(bundle, tmp_path, resume=True)
    assert run.skipped == [1, 2, 5] and run.written == [3, 4, 6]
    same_frames(reference, tmp_path, FRAMES)


def test_killed_worker_is_retried(cluster, bundle, reference, tmp_path) -> None:
    killer = Killer(SLOW_FRAME, times=1)
    killer.start()
    run = render_frames_ray(bundle, tmp_path, retries=2)
    killer.stop.set()
    assert killer.killed == 1, "the test never saw frame 3's worker to kill it"
    assert run.written == list(FRAMES) and not run.failed
    same_frames(reference, tmp_path, FRAMES)


def test_frame_that_keeps_failing_is_named(cluster, bundle, reference, tmp_path,
                                           capsys) -> None:
    killer = Killer(SLOW_FRAME, times=2)  # the first try and its one retry
    killer.start()
    code = main(["render-frames", str(bundle), "--out", str(tmp_path), "--ray",
                 "--retries", "1", "--no-progress"])
    killer.stop.set()
    out = capsys.readouterr().out
    assert killer.killed == 2
    assert code == 1
    assert f"frame {SLOW_FRAME} failed" in out and "--resume" in out
    others = [n for n in FRAMES if n != SLOW_FRAME]
    same_frames(reference, tmp_path, others)
    assert not any(p.exists() for p in frame_paths(tmp_path, SLOW_FRAME))


def test_missing_extra_is_named(bundle, tmp_path, monkeypatch, capsys) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    code = main(["render-frames", str(bundle), "--out", str(tmp_path), "--ray", "local"])
    assert code == 2
    assert 'pip install "scenesort[cluster]"' in capsys.readouterr().out
    assert not list(tmp_path.iterdir())
