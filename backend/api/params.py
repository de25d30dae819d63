"""Path and query parameters that several routes share, with their bounds."""

from __future__ import annotations

from typing import Annotated

from fastapi import Path, Query
from scenesort.backend.wire import binary as wire

SceneId = Annotated[
    str, Path(pattern=r"^[0-9a-f]{32}$", description="32 hex characters (see docs/api.md)")
]
JobId = Annotated[str, Path(pattern=r"^[0-9a-f]{16}$", description="16 hex characters")]
# The counts and flags of a scene or mesh body.
Vertices = Annotated[int, Query(ge=1, le=wire.MAX_INDEXABLE_VERTICES)]
Triangles = Annotated[int, Query(ge=1, le=2**31 - 1)]
Normals = Annotated[bool, Query(description="the body ends with T*9 float32 corner normals "
                                "(smooth shading)")]
Offsets = Annotated[bool, Query(description="after the normals, T float32 shadow terminator "
                                "offsets")]
