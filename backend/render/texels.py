"""A mesh's texture space as bake points: which triangle (and where in it) each texel
centre of a size x size image lies on, and a margin grown around the baked texels, as
Blender's bake does it (texel centres at ((i + 0.5) / size, (j + 0.5) / size), row 0 at
v = 0; the margin's "extend" mode: each ring takes the mean of its baked neighbours)."""

from __future__ import annotations

import numpy as np

EDGE_EPS = 1e-7  # barycentric slack: a centre exactly on a shared edge belongs to one of them


def rasterize(uv: np.ndarray, size: int) -> tuple[np.ndarray, ...]:
    """The covered texels of triangles with texture coordinates `uv` ((M, 3, 2), in [0, 1]
    for the image): texel indices (row-major from v = 0) and, per texel, its triangle and
    the barycentric weights u, v of the triangle's second and third corner. A texel
    covered twice keeps the lower triangle; triangles without area in texture space cover
    nothing."""
    p = np.asarray(uv, np.float64) * size - 0.5  # texel centres at integers
    lo = np.clip(np.floor(p.min(axis=1)), 0, size - 1).astype(np.int64)
    hi = np.clip(np.ceil(p.max(axis=1)), 0, size - 1).astype(np.int64)
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    spans = np.where(det != 0.0, (hi - lo + 1).prod(axis=1), 0)
    tri = np.repeat(np.arange(len(p)), spans)
    local = np.arange(len(tri)) - np.repeat(np.cumsum(spans) - spans, spans)
    width = (hi - lo + 1)[tri, 0]
    x = lo[tri, 0] + local % width
    y = lo[tri, 1] + local // width
    d = np.stack([x, y], axis=1) - p[tri, 0]
    a = (d[:, 0] * e2[tri, 1] - d[:, 1] * e2[tri, 0]) / det[tri]  # second corner's weight
    b = (e1[tri, 0] * d[:, 1] - e1[tri, 1] * d[:, 0]) / det[tri]  # third corner's
    inside = (a >= -EDGE_EPS) & (b >= -EDGE_EPS) & (a + b <= 1.0 + EDGE_EPS)
    texel = (y * size + x)[inside]
    texel, first = np.unique(texel, return_index=True)
    a = np.clip(a[inside][first], 0.0, 1.0)
    b = np.clip(b[inside][first], 0.0, 1.0 - a)
    return (texel.astype(np.int64), tri[inside][first].astype(np.int32),
            a.astype(np.float32), b.astype(np.float32))


def extend_margin(image: np.ndarray, covered: np.ndarray, margin: int) -> np.ndarray:
    """`image` ((size, size)) with `margin` rings of texels grown around the covered ones,
    each ring the mean of its covered 8-neighbours (Blender's Extend margin)."""
    out = np.where(covered, image, 0.0).astype(np.float32)
    done = covered.copy()
    for _ in range(margin):
        total = np.zeros_like(out)
        count = np.zeros(out.shape, np.int32)
        padded_v, padded_m = np.pad(out, 1), np.pad(done, 1)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if dy or dx:
                    window = (slice(1 + dy, 1 + dy + out.shape[0]),
                              slice(1 + dx, 1 + dx + out.shape[1]))
                    total += np.where(padded_m[window], padded_v[window], 0.0)
                    count += padded_m[window]
        ring = ~done & (count > 0)
        if not ring.any():
            break
        out[ring] = total[ring] / count[ring]
        done |= ring
    return out
