"""Statistics records: the typed dataclasses in which builds, traces and renders report
what they did and what it cost (`BvhStats`, `SceneStats`, `DacrtStats`, AO's timings).

Read them as attributes; `to_dict()` gives the fields for JSON. A field declared with
`unset()` is None until it applies (a refit's figures after a build, the other DACRT
variant's counts, the denoise time of an image not denoised) and left out of `to_dict()`
while it is None.
"""

from __future__ import annotations

from dataclasses import Field, field, fields
from typing import Any

_UNSET = "record.unset"  # field metadata: left out of to_dict() while None


def unset() -> Field:
    """A field that is None until it applies (`dataclasses.field`), and left out of
    `to_dict()` until then."""
    return field(default=None, metadata={_UNSET: True})


class Record:
    """Base of a statistics dataclass: its fields for JSON, and filling a mutable one."""

    __slots__ = ()

    def to_dict(self) -> dict[str, Any]:
        """The fields by name, in their order, for JSON (a dict field copied); those
        declared with `unset()` left out while None."""
        out = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if value is None and f.metadata.get(_UNSET):
                continue
            out[f.name] = dict(value) if isinstance(value, dict) else value
        return out

    def fill(self, **values: Any) -> None:
        """Set these fields (of a mutable record; an unknown name raises AttributeError)."""
        for name, value in values.items():
            setattr(self, name, value)
