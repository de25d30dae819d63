"""The byte-bounded LRU store (backend/work/store.py)."""

from __future__ import annotations

import pytest
from scenesort.backend.work.store import Store, bvh_key


def test_least_recently_used_is_evicted_first() -> None:
    store = Store(max_bytes=100)
    store.put("a", "A", 40)
    store.put("b", "B", 40)
    assert store.get("a") == "A"  # a is now newer than b
    assert store.put("c", "C", 40) == ["b"]
    assert "a" in store and "c" in store and "b" not in store
    assert store.usage()["bytes"] == 80


def test_a_scenes_bvhs_go_with_it() -> None:
    store = Store(max_bytes=100)
    store.put("s1", "scene", 30)
    store.put(bvh_key("s1", "sah", 8), "bvh", 30)
    store.put("s2", "scene", 30)
    store.get("s2")
    evicted = store.put("s3", "scene", 30)  # over by 20: s1 is oldest, and takes its BVH
    assert sorted(evicted) == sorted(["s1", bvh_key("s1", "sah", 8)])
    assert store.usage() == {"bytes": 60, "max_bytes": 100, "scenes": 2, "bvhs": 0, "evictions": 2}


def test_new_bvh_never_evicts_its_own_scene() -> None:
    store = Store(max_bytes=100)
    store.put("s1", "scene", 60)
    assert store.put(bvh_key("s1", "median", 4), "bvh", 60) == []
    assert "s1" in store and store.usage()["bytes"] == 120  # over budget: newest pair kept


def test_replacing_a_key_does_not_double_count() -> None:
    store = Store(max_bytes=100)
    store.put("a", 1, 50)
    store.put("a", 2, 70)
    assert store.get("a") == 2 and store.usage()["bytes"] == 70


def test_latest_with_prefix_finds_the_most_recent_bvh() -> None:
    store = Store(max_bytes=1000)
    store.put("s", "scene", 1)
    store.put(bvh_key("s", "sah", 8), "sah8", 1)
    store.put(bvh_key("s", "median", 8), "median8", 1)
    store.get(bvh_key("s", "sah", 8))
    assert store.latest_with_prefix("s/bvh/") == (bvh_key("s", "sah", 8), "sah8")
    assert store.latest_with_prefix("t/bvh/") is None


def test_budget_must_be_positive() -> None:
    with pytest.raises(ValueError, match="max_bytes"):
        Store(0)


def test_a_real_bvh_is_charged_for_each_of_its_arrays_once(box_scene) -> None:
    """The cache budget counts the BVH's tree, not just its inputs, and its mesh once: on
    CPU the device mesh (in the Bvh, its DeviceMesh and its struct) is the input arrays."""
    from scenesort.backend.work.store import bvh_nbytes

    from scenesort import kernels

    bvh = kernels.build_bvh(*box_scene, device="cpu")
    inputs = bvh.vertices.nbytes + bvh.indices.nbytes
    assert bvh.stats.bvh_bytes > 32 * bvh.stats.nodes
    assert bvh_nbytes(bvh) == inputs + bvh.stats.bvh_bytes + bvh.bounds.nbytes
