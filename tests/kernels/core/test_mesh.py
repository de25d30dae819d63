"""A scene's device arrays: made once per mesh and reused by the BVH, AO and DACRT."""

from __future__ import annotations

import numpy as np
import pytest
from scenesort.kernels.core import DeviceMesh, degenerate_mask
from scenesort.kernels.render import tracers

from scenesort import kernels

from ..reference import degenerate_triangles, random_rays, random_soup


def test_valid_ids_and_soup_are_made_once(device):
    rng = np.random.default_rng(4)
    v, f = random_soup(rng, 300)
    f = np.vstack([f, [[0, 0, 1], [2, 3, 3], [4, 4, 4]]]).astype(np.int32)  # zero area
    mesh = DeviceMesh(v, f, device)
    ids = mesh.valid_ids()
    assert np.array_equal(ids, np.flatnonzero(~degenerate_triangles(v, f)))
    assert np.array_equal(ids, np.flatnonzero(~degenerate_mask(v, f, "cpu")))
    assert mesh.valid_ids() is ids and len(ids) == len(f) - 3
    soup = mesh.soup()
    assert mesh.soup() is soup
    verts, lo, hi = (a.numpy() for a in soup)
    corners = v[f]
    assert np.array_equal(verts.reshape(-1, 3, 3), corners)
    assert np.array_equal(lo, corners.min(axis=1)) and np.array_equal(hi, corners.max(axis=1))
    assert mesh.nbytes == sum(a.capacity for a in (mesh.v, mesh.f, *soup))


def test_bad_meshes_are_rejected_when_made(device):
    v, f = random_soup(np.random.default_rng(1), 10)
    with pytest.raises(ValueError, match="indices must lie in"):
        DeviceMesh(v, f + 100, device)


@pytest.mark.parametrize("engine", ["bvh", "dacrt"])
def test_renders_reuse_the_bvh_mesh(engine, monkeypatch, device):
    """AO copies no mesh to the device per render: the BVH's arrays serve every call (with
    DACRT its triangle arrays too, made at the first round)."""
    rng = np.random.default_rng(2)
    v, f = random_soup(rng, 400)
    o, d = random_rays(rng, 500, -0.5, 1.5)
    bvh = kernels.build_bvh(v, f, device=device)
    made = []
    real_init = DeviceMesh.__init__

    def counting_init(self, *args, **kwargs):
        made.append(1)
        real_init(self, *args, **kwargs)

    monkeypatch.setattr(DeviceMesh, "__init__", counting_init)
    first = kernels.render_ao(bvh, o, d, spp=4, engine=engine)
    soup = bvh.mesh._soup
    again = kernels.render_ao(bvh, o, d, spp=4, engine=engine)
    assert not made and tracers.scene_mesh(bvh) is bvh.mesh
    assert (soup is not None) == (engine == "dacrt") and bvh.mesh._soup is soup
    assert np.array_equal(first.ao, again.ao)
