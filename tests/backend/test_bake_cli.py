"""`scenesort bake MESH` and its texture space: texel centres against a brute-force
point-in-triangle test, the Extend margin, the baked values against the engine's
`surface_ao` on the same points, the files it writes, and clear errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image
from scenesort.backend.commands import main
from scenesort.backend.render.texels import extend_margin, rasterize

from scenesort import kernels


def test_rasterize_finds_exactly_the_texel_centres_inside_each_triangle() -> None:
    rng = np.random.default_rng(3)
    size = 24
    uv = rng.random((40, 3, 2))
    texels, tri, a, b = rasterize(uv, size)
    centres = (np.stack(np.meshgrid(np.arange(size), np.arange(size)), -1).reshape(-1, 2)
               + 0.5) / size  # (x, y) per row-major texel, row 0 at v = 0
    inside = np.zeros((len(uv), size * size), bool)
    for k, (p0, p1, p2) in enumerate(uv):
        m = np.array([p1 - p0, p2 - p0]).T
        w = np.linalg.solve(m, (centres - p0).T).T
        inside[k] = (w >= 1e-9).all(1) & (w.sum(1) <= 1 - 1e-9)
    strictly = np.flatnonzero(inside.any(0))
    assert set(strictly) <= set(texels)  # every centre strictly inside is found
    assert len(texels) <= len(np.flatnonzero((inside | _on_edge(uv, centres)).any(0)))
    assert np.all(inside[tri, texels] | _on_edge(uv, centres)[tri, texels])
    point = (1 - a - b)[:, None] * uv[tri, 0] + a[:, None] * uv[tri, 1] + b[:, None] * uv[tri, 2]
    np.testing.assert_allclose(point, centres[texels], atol=1e-6)  # the weights are right


def _on_edge(uv: np.ndarray, centres: np.ndarray) -> np.ndarray:
    out = np.zeros((len(uv), len(centres)), bool)
    for k, (p0, p1, p2) in enumerate(uv):
        m = np.array([p1 - p0, p2 - p0]).T
        w = np.linalg.solve(m, (centres - p0).T).T
        out[k] = (w >= -1e-6).all(1) & (w.sum(1) <= 1 + 1e-6)
    return out


def test_extend_margin_grows_rings_of_neighbour_means() -> None:
    image = np.zeros((5, 5), np.float32)
    covered = np.zeros((5, 5), bool)
    image[2, 2], covered[2, 2] = 0.8, True
    image[2, 3], covered[2, 3] = 0.4, True
    out = extend_margin(image, covered, 1)
    assert out[2, 2] == np.float32(0.8) and out[2, 1] == np.float32(0.8)  # one neighbour
    assert out[1, 2] == np.float32(0.6)  # two: their mean
    assert out[0, 0] == 0.0  # beyond the margin
    assert np.all(extend_margin(image, covered, 3)[[0, 4], :] > 0.0)


def _floor_under_a_roof(path: Path) -> trimesh.Trimesh:
    """A unit floor, UV-mapped to the whole texture, and a small roof over its left half
    whose texture coordinates have no area (it occludes, it is not baked)."""
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
                  [0, 0, 0.1], [0, 1, 0.1], [0.5, 0, 0.1], [0.5, 1, 0.1]], float)
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 7], [4, 7, 6]])
    uv = np.concatenate([v[:4, :2], np.zeros((4, 2))])
    mesh = trimesh.Trimesh(v, f, process=False,
                           visual=trimesh.visual.TextureVisuals(uv=uv))  # fmt: skip
    mesh.export(path)
    return mesh


def test_the_bake_is_surface_ao_at_the_texels_with_a_margin(tmp_path) -> None:
    obj = tmp_path / "floor.obj"
    _floor_under_a_roof(obj)
    out = tmp_path / "ao.npy"
    assert main(["bake", str(obj), "--size", "32", "--spp", "16", "--seed", "4",
                 "--distance", "1", "--margin", "2", "--out", str(out)]) == 0  # fmt: skip
    baked = np.load(out)
    from scenesort.backend.commands.bake import load_uv_mesh

    vertices, indices, uv, _ = load_uv_mesh(obj, smooth=False)
    texels, tri, a, b = rasterize(uv, 32)
    bvh = kernels.build_bvh(vertices, indices)
    expected = kernels.surface_ao(bvh, tri, a, b, spp=16, seed=4, distance=1.0)
    np.testing.assert_array_equal(baked.ravel()[texels], expected.ao)
    assert len(texels) == 32 * 32  # the floor's UVs cover every texel centre
    assert baked[:, :12].mean() < 0.3 and baked[:, 20:].mean() > 0.6  # under the roof: dark
    png = tmp_path / "ao.png"
    assert main(["bake", str(obj), "--size", "32", "--spp", "16", "--seed", "4",
                 "--distance", "1", "--out", str(png)]) == 0  # fmt: skip
    grey = np.asarray(Image.open(png)).astype(np.float64) / 65535.0
    np.testing.assert_allclose(grey[::-1], baked, atol=1e-4)  # image files: top row first
    import OpenEXR

    exr = tmp_path / "ao.exr"
    assert main(["bake", str(obj), "--size", "32", "--spp", "16", "--seed", "4",
                 "--distance", "1", "--out", str(exr)]) == 0  # fmt: skip
    with OpenEXR.File(str(exr)) as f:
        np.testing.assert_array_equal(f.channels()["Y"].pixels[::-1], baked)


@pytest.mark.parametrize(("argv", "message"), [
    (["--out", "ao.jpg"], "--out must end in one of .png, .exr, .npy"),
    (["--size", "0"], "--size must be >= 1"),
    (["--spp", "0"], "--spp"),
])  # fmt: skip
def test_bad_flags_are_refused_by_name(tmp_path, capsys, argv, message) -> None:
    obj = tmp_path / "floor.obj"
    _floor_under_a_roof(obj)
    assert main(["bake", str(obj), *argv]) == 2
    assert message in " ".join(capsys.readouterr().out.split())  # rich wraps lines


def test_a_mesh_without_texture_coordinates_is_refused(tmp_path, capsys) -> None:
    ply = tmp_path / "plain.ply"
    trimesh.creation.box().export(ply)
    assert main(["bake", str(ply), "--out", str(tmp_path / "x.png")]) == 2
    assert "has no texture coordinates: unwrap it" in " ".join(capsys.readouterr().out.split())
    assert not (tmp_path / "x.png").exists()
