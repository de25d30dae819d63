"""`scenesort render`: the default scene, shared scenes by name or path, cameras, outputs,
the timing table and bad input (run in-process through the real command-line entry)."""

from __future__ import annotations

import json
import re
import sys

import numpy as np
import pytest
from PIL import Image
from scenesort.backend.commands import main
from scenesort.backend.render.scenes import shared_scene, shared_scenes_dir
from scenesort.kernels import Camera

from scenesort import kernels


@pytest.fixture(scope="module")
def scenes_dir():
    folder = shared_scenes_dir()
    if folder is None:
        pytest.fail("../shared/scenes not found: set SCENESORT_SCENES to the scenes folder")
    return folder


def test_no_arguments_renders_the_default_scene(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["render", "--no-progress"]) == 0
    image = np.asarray(Image.open(tmp_path / "ao.png"))
    assert image.shape == (480, 640) and image.dtype == np.uint8
    assert image.min() < 128 < image.max()  # corners and contacts are dark, open floor light
    out = capsys.readouterr().out
    for word in ("default", "load", "compile", "build", "primary", "occlusion", "total",
                 "MRays/s"):
        assert word in out


def test_shared_scene_by_name_writes_png_and_npy(tmp_path, capsys, scenes_dir):
    png, npy = tmp_path / "s.png", tmp_path / "sub" / "s.npy"
    rc = main(
        [
            "render",
            "--scene",
            "sponza",
            "--width",
            "64",
            "--height",
            "48",
            "--spp",
            "4",
            "--seed",
            "3",
            "--out",
            str(png),
            "--npy",
            str(npy),
        ]
    )
    assert rc == 0
    ao = np.load(npy)
    assert ao.shape == (48, 64) and ao.dtype == np.float32
    assert np.array_equal(np.asarray(Image.open(png)), np.rint(ao * 255).astype(np.uint8))
    # The same as calling the engine with the scene's own camera.
    scene = shared_scene("sponza", 64, 48)
    o, d, tmin, tmax = scene.camera.rays()
    bvh = kernels.build_bvh(scene.vertices, scene.indices)
    expected = kernels.ambient_occlusion(bvh, o, d, spp=4, seed=3, tmin=tmin, tmax=tmax)
    assert np.array_equal(ao.ravel(), expected)
    assert "sponza" in capsys.readouterr().out


def test_filter_width_renders_through_the_pixel_filter(tmp_path, capsys, scenes_dir):
    """--pixel-filter and --filter-width: the image is render_film's through that filter,
    the table names it; with DACRT the render says it renders pixel centres."""
    npy = tmp_path / "f.npy"
    args = ["render", "--scene", "sponza", "--width", "64", "--height", "48", "--spp", "4",
            "--seed", "3", "--out", str(tmp_path / "f.png"), "--npy", str(npy),
            "--no-progress"]
    assert main([*args, "--pixel-filter", "GAUSSIAN", "--filter-width", "1.5"]) == 0
    scene = shared_scene("sponza", 64, 48)
    bvh = kernels.build_bvh(scene.vertices, scene.indices)
    film = kernels.render_film(bvh, scene.camera, spp=4, seed=3, pixel_filter="GAUSSIAN",
                               filter_width=1.5)
    assert np.array_equal(np.load(npy), film.ao)
    out = capsys.readouterr().out
    assert "GAUSSIAN 1.5 px" in out and "film" in out
    assert main([*args, "--engine", "dacrt", "--filter-width", "1.5"]) == 0
    assert "pixel centres: engine dacrt" in " ".join(capsys.readouterr().out.split())


def test_ply_path_with_camera_file_and_target_error(tmp_path, scenes_dir, capsys):
    cam = {
        "position": [0.1111, 0.2167, 0.4248],
        "look_at": [-0.0168, 0.1102, -0.0015],
        "up": [0, 1, 0],
        "fov_y_deg": 35,
    }
    cam_path = tmp_path / "cam.json"
    cam_path.write_text(json.dumps(cam))
    npy = tmp_path / "b.npy"
    rc = main(
        [
            "render",
            "--scene",
            str(scenes_dir / "bunny.ply"),
            "--camera",
            str(cam_path),
            "--width",
            "40",
            "--height",
            "30",
            "--target-error",
            "0.1",
            "--no-progress",
            "--out",
            str(tmp_path / "b.png"),
            "--npy",
            str(npy),
        ]
    )
    assert rc == 0
    ao = np.load(npy)
    camera = Camera.look_at(cam["position"], cam["look_at"], cam["up"], 35, 40, 30)
    hit = kernels.trace(kernels.build_bvh(*_bunny(scenes_dir)), *camera.rays()[:2]).hit
    assert 0.05 < hit.mean() < 0.9  # the file camera, not the framing one, was used
    assert np.all(ao.ravel()[~hit] == 1.0) and ao.ravel()[hit].min() < 1.0
    out = capsys.readouterr().out  # the table's title: what the render achieved
    assert re.search(r"est\. RMSE 0\.\d{4} \(AO\s+units,\s+hit\s+pixels\)", out), out


def _bunny(folder):
    from scenesort.backend.render.scenes import load_mesh

    return load_mesh(folder / "bunny.ply")


@pytest.mark.parametrize(
    "argv,message",
    [
        (["--width", "0"], "--width"),
        (["--scene", "no-such-scene"], "no-such-scene"),
        (["--distance", "-1"], "distance"),
        (["--scene", "missing.ply"], "missing.ply"),
    ],
)
def test_bad_input_is_reported(tmp_path, capsys, argv, message, scenes_dir):
    rc = main(["render", "--no-progress", "--out", str(tmp_path / "x.png"), *argv])
    assert rc == 2
    assert message in capsys.readouterr().out
    assert not (tmp_path / "x.png").exists()


def test_denoise_flag(tmp_path, capsys, scenes_dir, monkeypatch):
    """--denoise writes `render_ao(denoise=True)`'s image and says the estimate is the raw
    render's; without pyoidn it is a clear error naming the extra."""
    npy = tmp_path / "d.npy"
    argv = ["render", "--no-progress", "--scene", "bunny", "--width", "64", "--height", "48",
            "--spp", "2", "--out", str(tmp_path / "d.png"), "--npy", str(npy), "--denoise"]
    assert main(argv) == 0
    assert "before denoising" in capsys.readouterr().out
    scene = shared_scene("bunny", 64, 48)
    o, d, tmin, tmax = scene.camera.rays()
    bvh = kernels.build_bvh(scene.vertices, scene.indices)
    expected = kernels.render_ao(bvh, o, d, spp=2, tmin=tmin, tmax=tmax, denoise=True,
                                 image_shape=(48, 64))
    np.testing.assert_allclose(np.load(npy).ravel(), expected.ao, atol=1e-6)
    monkeypatch.setitem(sys.modules, "pyoidn", None)
    assert main(argv) == 2
    assert 'pip install "scenesort[denoise]"' in capsys.readouterr().out.replace("\n", "")
