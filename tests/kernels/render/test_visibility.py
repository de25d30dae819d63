"""Ray visibility and holdout in `render_ao`: what the camera sees (`bvh`), what occludes
(`occluders`) and what is held out (`holdout`), as Cycles' AO pass treats an object's
Camera and Shadow ray visibility and its holdout. Each case is checked pixel by pixel
against renders that hold only the objects the rule says count: the same samples of the
same hits give the same AO, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scenesort.kernels import Camera

from scenesort import kernels

CAMERA = Camera.look_at((0.0, -3.0, 2.2), (0.0, 0.0, 0.3), (0, 0, 1), 40, 48, 36)
DIST = 1.0
SPP = 16


def plane() -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[-3, -3, 0], [3, -3, 0], [3, 3, 0], [-3, 3, 0]], np.float32)
    return v, np.array([[0, 1, 2], [0, 2, 3]], np.int32)


def box() -> tuple[np.ndarray, np.ndarray]:
    b = trimesh.creation.box(extents=(0.8, 0.8, 0.8))
    return np.asarray(b.vertices, np.float32), np.asarray(b.faces, np.int32)


TRANSFORMS = np.array([np.eye(3, 4), np.eye(3, 4), np.eye(3, 4)], np.float32)
TRANSFORMS[1, :, 3] = (-0.5, 0.0, 0.45)  # box A, just above the plane
TRANSFORMS[2, :, 3] = (0.7, 0.3, 0.45)  # box B


@pytest.fixture(scope="module")
def parts():
    """The plane and two boxes, as a two-level scene per subset of them (instance indices
    kept: 0 plane, 1 box A, 2 box B), and flattened, one Bvh per subset."""
    meshes = [kernels.build_bvh(*plane()), kernels.build_bvh(*box())]
    ids = np.array([0, 1, 1], np.int32)

    def scene(*keep: int):
        return kernels.build_scene(meshes, ids, TRANSFORMS,
                                   visible=np.isin(np.arange(3), keep))

    def flat(*keep: int):
        vs, fs, base = [], [], 0
        for k in keep:
            v, f = (plane(), box(), box())[k]
            vs.append(v + TRANSFORMS[k, :, 3])
            fs.append(f + base)
            base += len(v)
        return kernels.build_bvh(np.concatenate(vs), np.concatenate(fs))

    return {"scene": scene, "flat": flat}


def render(camera_sees, **kw):
    o, d, tmin, tmax = CAMERA.rays()
    return kernels.render_ao(camera_sees, o, d, spp=SPP, distance=DIST, tmin=tmin, tmax=tmax,
                             **kw)


def first_hit(traced) -> kernels.Hits:
    o, d, tmin, tmax = CAMERA.rays()
    return kernels.trace(traced, o, d, tmin, tmax)


@pytest.mark.parametrize("kind", ["scene", "flat"])
def test_default_occluders_are_the_camera_geometry(parts, kind):
    every = parts[kind](0, 1, 2)
    a, b = render(every), render(every, occluders=every)
    assert np.array_equal(a.ao, b.ao) and a.holdout is None


@pytest.mark.parametrize("kind", ["scene", "flat"])
def test_camera_invisible_object_occludes_unseen(parts, kind):
    make = parts[kind]
    every = render(make(0, 1, 2))
    unseen_a = render(make(0, 2), occluders=make(0, 1, 2))
    hits_every, hits_unseen = first_hit(make(0, 1, 2)), first_hit(make(0, 2))
    through_a = hits_every.hit & (hits_every.t < hits_unseen.t)  # box A in front
    assert through_a.sum() > 50
    # where box A would be seen, the plane behind it is, darkened by A (it still occludes)
    assert (unseen_a.spp_used[through_a] > 0).all()
    seen_alone = render(make(0, 2))  # the same hits with nothing of A
    assert unseen_a.ao[through_a].mean() < seen_alone.ao[through_a].mean() - 0.05
    # elsewhere nothing changed: the same hits, the same occluders
    same = ~through_a
    assert np.array_equal(unseen_a.ao[same], every.ao[same])


@pytest.mark.parametrize("kind", ["scene", "flat"])
def test_shadow_invisible_object_is_seen_and_occludes_nothing(parts, kind):
    make = parts[kind]
    no_shadow_a = render(make(0, 1, 2), occluders=make(0, 2))
    without_a = render(make(0, 2))
    every = first_hit(make(0, 1, 2))
    on_a = every.hit & (every.instance == 1) if kind == "scene" else None
    hits_without = first_hit(make(0, 2))
    seen_a = every.hit & (every.t < hits_without.t)
    if on_a is not None:
        assert np.array_equal(on_a, seen_a)
    assert seen_a.sum() > 50 and (no_shadow_a.spp_used[seen_a] > 0).all()
    # every pixel that does not see A is exactly the render without A: A occludes nothing
    rest = ~seen_a
    assert np.array_equal(no_shadow_a.ao[rest], without_a.ao[rest])
    # and the plane near A is lighter than where A occludes
    with_a = render(make(0, 1, 2))
    assert no_shadow_a.ao[rest].mean() > with_a.ao[rest].mean() + 0.01


@pytest.mark.parametrize("kind", ["scene", "flat"])
def test_holdout_gives_ao_zero_and_no_samples_and_still_occludes(parts, kind):
    make = parts[kind]
    every = make(0, 1, 2)
    held = render(make(0, 2), holdout=make(1), occluders=every)
    plain = render(every)
    hits_every, hits_rest = first_hit(every), first_hit(make(0, 2))
    on_a = hits_every.hit & (hits_every.t < hits_rest.t)
    assert on_a.sum() > 50
    assert np.array_equal(held.holdout, on_a)
    assert (held.ao[on_a] == 0.0).all() and (held.spp_used[on_a] == 0).all()
    # everything else is the render with A an ordinary, occluding object
    assert np.array_equal(held.ao[~on_a], plain.ao[~on_a])
    assert np.array_equal(held.spp_used[~on_a], plain.spp_used[~on_a])


def test_holdout_behind_a_seen_object_holds_nothing_out(parts):
    """A holdout hidden behind a visible object: the nearer, visible hit wins."""
    make = parts["scene"]
    # seen from above, box A's top is in front of the plane: the plane as holdout is
    # behind A wherever A is seen
    held = render(make(1, 2), holdout=make(0), occluders=make(0, 1, 2))
    boxes = first_hit(make(1, 2))
    assert boxes.hit.sum() > 50
    assert not held.holdout[boxes.hit].any()
    assert held.holdout[~boxes.hit].mean() > 0.5  # the plane around them is held out


def test_visibility_arguments_are_checked(parts):
    make = parts["scene"]
    with pytest.raises(ValueError, match="dacrt"):
        render(make(0), occluders=make(0, 1), engine="dacrt")
