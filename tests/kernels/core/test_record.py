"""Statistics records: typed fields, and a read-only mapping view without unset fields."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
from scenesort.kernels.core.record import Record, unset

pytestmark = pytest.mark.host_only


@dataclass(slots=True)
class Example(Record):
    build_ms: float
    rounds: int = 0
    refit_ms: float | None = unset()
    estimate: float | None = None  # None is a value here: always in the view


def test_mapping_view_in_field_order_without_unset_fields():
    s = Example(build_ms=1.5)
    assert dict(s) == {"build_ms": 1.5, "rounds": 0, "estimate": None}
    assert s["build_ms"] == 1.5 and s.get("refit_ms", -1.0) == -1.0 and "refit_ms" not in s
    with pytest.raises(KeyError):
        s["refit_ms"]
    s.fill(refit_ms=2.0)
    assert list(s) == ["build_ms", "rounds", "refit_ms", "estimate"] and s["refit_ms"] == 2.0
    with pytest.raises(AttributeError):
        s.fill(refits=1)  # a typo is no new field
