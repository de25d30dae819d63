"""Statistics records: typed fields read as attributes, and `to_dict()` for JSON without
unset fields."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import pytest
from scenesort.kernels.core.record import Record, unset

pytestmark = pytest.mark.host_only


@dataclass(slots=True)
class Example(Record):
    build_ms: float
    rounds: int = 0
    refit_ms: float | None = unset()
    estimate: float | None = None  # None is a value here: always in to_dict()
    phase_ms: dict[str, float] | None = None


def test_to_dict_in_field_order_without_unset_fields():
    s = Example(build_ms=1.5)
    assert s.to_dict() == {"build_ms": 1.5, "rounds": 0, "estimate": None, "phase_ms": None}
    s.fill(refit_ms=2.0, phase_ms={"nodes": 0.5})
    out = s.to_dict()
    assert list(out) == ["build_ms", "rounds", "refit_ms", "estimate", "phase_ms"]
    assert out["refit_ms"] == 2.0
    out["phase_ms"]["nodes"] = 9.0  # a copy: the record keeps its figures
    assert s.phase_ms == {"nodes": 0.5}
    with pytest.raises(AttributeError):
        s.fill(refits=1)  # a typo is no new field


def test_a_record_is_read_as_attributes_not_as_a_mapping():
    s = Example(build_ms=1.5)
    assert not isinstance(s, Mapping)
    with pytest.raises(TypeError):
        s["build_ms"]  # noqa: B018
