"""Input checks shared by every entry point: ValueError naming the problem and the fix."""

from __future__ import annotations

import numpy as np

from scenesort.ao_options import AO_OPTIONS


def _float_array(a, name: str, width: int) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != 2 or a.shape[1] != width:
        raise ValueError(f"{name} must have shape (N, {width}), got {a.shape}")
    if a.dtype.kind != "f":  # (np.issubdtype's answer in a tenth of its 1 us)
        raise ValueError(f"{name} must be a float32 array, got dtype {a.dtype}")
    if a.dtype != np.float32 and a.size:
        big = np.abs(np.where(np.isfinite(a), a, 0.0)).max()
        if big > np.finfo(np.float32).max:
            raise ValueError(f"{name} has values beyond the float32 range (|x| up to {big:.3g}); "
                             "the engine computes in float32: rescale the input")
    a = np.ascontiguousarray(a, dtype=np.float32)
    if np.isfinite(a).all():
        return a
    bad = ~np.isfinite(a).all(axis=1)
    if bad.any():
        raise ValueError(
            f"{name} contains NaN or Inf in {int(bad.sum())} rows (first: row "
            f"{int(np.flatnonzero(bad)[0])}); remove or fix them"
        )
    return a


def as_triangle_mesh(vertices, indices) -> tuple[np.ndarray, np.ndarray]:
    """Validated float32 (N,3) vertices and int32 (M,3) indices."""
    vertices = _float_array(vertices, "vertices", 3)
    idx = np.asarray(indices)
    if idx.ndim != 2 or idx.shape[1] != 3:
        raise ValueError(f"indices must have shape (M, 3), got {idx.shape}")
    if not np.issubdtype(idx.dtype, np.integer):
        raise ValueError(f"indices must be an int32 array, got dtype {idx.dtype}")
    if idx.size:
        lo, hi = int(idx.min()), int(idx.max())
        if lo < 0 or hi >= len(vertices):
            raise ValueError(
                f"indices must lie in [0, {len(vertices) - 1}] (the vertex count is "
                f"{len(vertices)}), found values in [{lo}, {hi}]"
            )
    return vertices, np.ascontiguousarray(idx, dtype=np.int32)


def as_rays(origins, directions) -> tuple[np.ndarray, np.ndarray]:
    """Validated float32 (R,3) origins and non-zero directions."""
    origins = _float_array(origins, "origins", 3)
    directions = _float_array(directions, "directions", 3)
    if len(origins) != len(directions):
        raise ValueError(
            f"origins and directions must have the same length, got {len(origins)} and "
            f"{len(directions)}"
        )
    if directions.all():  # no zero component at all (5 us for 10k rays, the rows 24 us)
        return origins, directions
    zero = (directions[:, 0] == 0.0) & (directions[:, 1] == 0.0) & (directions[:, 2] == 0.0)
    if zero.any():  # (columnwise: four times faster than a row reduction)
        raise ValueError(
            f"directions has {int(zero.sum())} zero-length rows (first: row "
            f"{int(np.flatnonzero(zero)[0])}); every ray needs a non-zero direction"
        )
    return origins, directions


def as_rays_unread(origins, directions) -> tuple[np.ndarray, np.ndarray]:
    """as_rays's shapes and dtypes without its pass over the values, for a kernel that
    checks each ray as it first reads it (core.ray.flag_invalid_rays) and a caller that
    then calls `refuse_flagged_rays`: float32 (R, 3) arrays of one length pass unread;
    anything else goes through as_rays (a conversion reads the values anyway)."""
    o, d = np.asarray(origins), np.asarray(directions)
    if (o.dtype == d.dtype == np.float32 and o.ndim == d.ndim == 2
            and o.shape[1] == d.shape[1] == 3 and len(o) == len(d)):
        return np.ascontiguousarray(o), np.ascontiguousarray(d)
    return as_rays(o, d)


def refuse_flagged_rays(flag, origins: np.ndarray, directions: np.ndarray) -> None:
    """as_rays's ValueError where a kernel flagged a ray it refuses (flag: the kernel's
    one-int array, numpy or Warp)."""
    if (flag if isinstance(flag, np.ndarray) else flag.numpy())[0]:
        as_rays(origins, directions)
        raise AssertionError("a kernel flagged a ray that as_rays accepts")


def as_surface_points(triangles, u, v, triangle_count: int) -> tuple[np.ndarray, ...]:
    """Validated int32 triangle indices in [0, triangle_count) and float32 barycentric
    weights u, v (of each triangle's second and third corner: u, v >= 0, u + v <= 1, with
    float32 rounding's slack), all of one length."""
    tri = np.asarray(triangles)
    if tri.ndim != 1 or not np.issubdtype(tri.dtype, np.integer):
        raise ValueError(f"triangles must be a 1-D integer array, got shape {tri.shape}, "
                         f"dtype {tri.dtype}")
    if tri.size and (int(tri.min()) < 0 or int(tri.max()) >= triangle_count):
        raise ValueError(f"triangles must lie in [0, {triangle_count - 1}] (the mesh has "
                         f"{triangle_count} triangles), found [{int(tri.min())}, "
                         f"{int(tri.max())}]")
    u = per_ray(u, len(tri), "u")
    v = per_ray(v, len(tri), "v")
    outside = ~((u >= 0.0) & (v >= 0.0) & (u + v <= 1.0 + 1e-6))  # NaN and inf too
    if outside.any():
        row = int(np.flatnonzero(outside)[0])
        raise ValueError(f"u and v must be barycentric weights (u, v >= 0, u + v <= 1); "
                         f"point {row} has u={u[row]}, v={v[row]}")
    return np.ascontiguousarray(tri, dtype=np.int32), u, v


def per_ray(value, count: int, name: str, *, keep_scalar: bool = False) -> np.ndarray:
    """A scalar or (R,) array as a float32 (R,) array, or with `keep_scalar` a scalar as a
    (1,) array for kernels that broadcast it; NaN is rejected, +-inf allowed."""
    if isinstance(value, float | int) and keep_scalar:  # a small call's fast path (~0.5 us)
        if value != value:
            raise ValueError(f"{name} contains NaN")
        return np.array((value,), dtype=np.float32)
    a = np.asarray(value, dtype=np.float32)
    if a.ndim == 0:
        a = a.reshape(1) if keep_scalar else np.full(count, a, dtype=np.float32)
    elif a.shape != (count,):
        raise ValueError(f"{name} must be a scalar or have shape ({count},), got {a.shape}")
    if np.isnan(a).any():
        raise ValueError(f"{name} contains NaN")
    return np.ascontiguousarray(a)


def ray_range(tmin, tmax, count: int, *, keep_scalar: bool = False) -> tuple[np.ndarray, ...]:
    """`per_ray` of both ends of the rays' [tmin, tmax], checked to be in order."""
    tmin = per_ray(tmin, count, "tmin", keep_scalar=keep_scalar)
    tmax = per_ray(tmax, count, "tmax", keep_scalar=keep_scalar)
    # two scalars compared as such: 0.2 us against 2 for the arrays
    if (tmax[0] < tmin[0]) if tmin.size == tmax.size == 1 else np.any(tmax < tmin):
        raise ValueError("tmax must be >= tmin for every ray")
    return tmin, tmax


def as_shading(normals, terminator_offset, triangles: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Per-corner shading normals and per-triangle terminator offsets, validated: None for
    `normals=None` (geometric normals), else (T, 3, 3) float32 normals with every corner
    scaled to unit length (a zero corner stays zero: three zero corners mark a flat
    triangle) and (T,) float32 offsets in [0, 1] (a scalar applies to every triangle)."""
    if normals is None:
        return None
    n = np.asarray(normals)
    if n.shape != (triangles, 3, 3):
        raise ValueError(f"normals must have shape ({triangles}, 3, 3) (one normal per corner "
                         f"of each triangle) or be None, got {n.shape}")
    if not np.issubdtype(n.dtype, np.floating):
        raise ValueError(f"normals must be a float32 array, got dtype {n.dtype}")
    n = np.asarray(n, dtype=np.float64)
    bad = ~np.isfinite(n).reshape(triangles, -1).all(axis=1)
    if bad.any():
        raise ValueError(f"normals contains NaN or Inf at {int(bad.sum())} triangles (first: "
                         f"triangle {int(np.flatnonzero(bad)[0])}); fix them or send zeros")
    length = np.linalg.norm(n, axis=2, keepdims=True)
    unit = np.divide(n, length, out=np.zeros_like(n), where=length > 0.0)
    return (np.ascontiguousarray(unit, dtype=np.float32),
            as_terminator_offsets(terminator_offset, triangles, "triangles"))


def as_terminator_offsets(terminator_offset, count: int, per: str) -> np.ndarray:
    """(count,) float32 shadow terminator offsets in [0, 1], one per triangle or instance
    (`per` names which); a scalar applies to all."""
    offsets = np.asarray(terminator_offset, dtype=np.float64)
    if offsets.ndim == 0:
        offsets = np.full(count, offsets)
    if offsets.shape != (count,):
        raise ValueError(f"terminator_offset must be a number or have shape ({count},) (one "
                         f"per {per}), got {offsets.shape}")
    spec = AO_OPTIONS["terminator_offset"]
    if not spec.within(offsets).all():
        raise ValueError(f"terminator_offset must lie {spec.range()} (Blender's Shadow "
                         "Terminator Geometry Offset), got values outside it")
    return np.ascontiguousarray(offsets, dtype=np.float32)
