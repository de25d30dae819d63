"""Statistics records: the typed dataclasses in which builds, traces and renders report
what they did and what it cost (`BvhStats`, `SceneStats`, `DacrtStats`, AO's timings).

A record also reads as a read-only mapping of its fields, in their order (`dict(stats)`
for JSON; `stats["build_ms"]`, `stats.get(...)` as the untyped dicts that records replaced
were read): a field declared with `unset()` is left out of that view while it is None,
as the dicts left out a key that did not apply (a refit's figures after a build, the other
DACRT variant's counts).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import Field, field, fields
from typing import Any

_UNSET = "record.unset"  # field metadata: left out of the mapping view while None


def unset() -> Field:
    """A field that is None until it applies (`dataclasses.field`), and left out of the
    mapping view until then."""
    return field(default=None, metadata={_UNSET: True})


class Record(Mapping[str, Any]):
    """Base of a statistics dataclass: the mapping view of its fields."""

    __slots__ = ()

    def __getitem__(self, name: str) -> Any:
        if name not in iter(self):
            raise KeyError(name)
        return getattr(self, name)

    def __iter__(self) -> Iterator[str]:
        for f in fields(self):
            if not (f.metadata.get(_UNSET) and getattr(self, f.name) is None):
                yield f.name

    def __len__(self) -> int:
        return sum(1 for _ in self)

    def fill(self, **values: Any) -> None:
        """Set these fields (of a mutable record; an unknown name raises AttributeError)."""
        for name, value in values.items():
            setattr(self, name, value)
