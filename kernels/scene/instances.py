"""Instances on the host: validated object-to-world transforms, their inverses, and the padded
world boxes the top level is built over (docs/robustness.md, "Instances").

Why the padding: a ray is traced in an instance as the object-space ray o' = fl(A (o - T)),
d' = fl(A d) (A = M^-1, computed in float64 and rounded once to float32), whose hits are
exact for that rounded ray. Mapped back, a hit point at parameter t lies within
|M| (|o' - A (o - T)| + t |d' - A d|) of the world ray's point o + t d, which is at most
u C (|o - T| + t |d|) componentwise (u = 2^-24, C = || |M| |A| ||_inf, the transform's
condition number in the infinity norm), and |o - T| <= t |d| + |o + t d - T|. So the world
point is within p + s t of the instance's world box, with p = u C R (R: the farthest the
box gets from T) and s = 2 u C ||d||_inf, plus the float32 rounding of the reported t
(u t ||d||) and of the watertight test around the triangle. The boxes are padded by K p
and the top level tests them with walls that move out by K s per unit t (kernels.scene.top:
`enter_padded_box`), with the safety factor K = 8 over these first-order bounds.
"""

from __future__ import annotations

import numpy as np

UNIT = 2.0**-24  # float32 unit roundoff
SAFETY = 8.0  # over the first-order bounds above


def as_instances(mesh_ids, transforms, meshes: int) -> tuple[np.ndarray, np.ndarray]:
    """Validated (I,) int32 mesh ids in [0, meshes) and (I, 3, 4) float32 object-to-world
    transforms (rows of the 3x4 matrix [M | T]), finite and invertible."""
    ids = np.asarray(mesh_ids)
    if ids.ndim != 1 or not np.issubdtype(ids.dtype, np.integer):
        raise ValueError(f"mesh_ids must be a 1-D int32 array, got shape {ids.shape} "
                         f"dtype {ids.dtype}")
    if ids.size and (ids.min() < 0 or ids.max() >= meshes):
        raise ValueError(f"mesh_ids must be in [0, {meshes}) (one per instance, indexing "
                         f"meshes), got values in [{ids.min()}, {ids.max()}]")
    m = np.asarray(transforms)
    if m.shape != (len(ids), 3, 4):
        raise ValueError(f"transforms must have shape ({len(ids)}, 3, 4) (a 3x4 object-to-"
                         f"world matrix per instance), got {m.shape}")
    if not np.issubdtype(m.dtype, np.floating):
        raise ValueError(f"transforms must be a float32 array, got dtype {m.dtype}")
    m = np.ascontiguousarray(m, np.float32)
    if not np.isfinite(m).all():
        bad = int(np.flatnonzero(~np.isfinite(m).reshape(len(m), -1).all(axis=1))[0])
        raise ValueError(f"transforms contain NaN or Inf (first: instance {bad})")
    det = np.linalg.det(m[:, :, :3].astype(np.float64)) if len(m) else np.zeros(0)
    lin = np.abs(m[:, :, :3].astype(np.float64)).max(axis=(1, 2)) if len(m) else det
    flat = ~(np.abs(det) > 1e-30 * np.maximum(lin, 1e-30) ** 3)
    if flat.any():
        raise ValueError(f"transforms must be invertible: instance {int(np.flatnonzero(flat)[0])}"
                         " has a singular 3x3 part (zero scale on some axis); leave it out")
    return ids.astype(np.int32), m


def instance_frames(transforms: np.ndarray) -> dict[str, np.ndarray]:
    """Per instance, in float64: the linear part M, its inverse A, the translation T, and
    the condition number C = || |M| |A| ||_inf (the rounding bound's factor, module doc)."""
    lin = transforms[:, :, :3].astype(np.float64)
    inv = np.linalg.inv(lin) if len(lin) else lin.copy()
    cond = np.einsum("nij,njk->nik", np.abs(lin), np.abs(inv)).sum(axis=2).max(axis=1)
    return {"lin": lin, "inv": inv, "trans": transforms[:, :, 3].astype(np.float64),
            "cond": cond}


def round_out(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """float64 boxes as float32 boxes that contain them."""
    lo32 = lo.astype(np.float32)
    hi32 = hi.astype(np.float32)
    lo32 = np.where(lo32 > lo, np.nextafter(lo32, np.float32(-np.inf)), lo32)
    hi32 = np.where(hi32 < hi, np.nextafter(hi32, np.float32(np.inf)), hi32)
    return lo32, hi32


def world_boxes(frames: dict, mesh_ids: np.ndarray, mesh_bounds: np.ndarray,
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(lo, hi) float32 world boxes of the instances, each the exact image of its mesh's
    object box padded by SAFETY u C R (module doc), the same unpadded (for the scene's
    bounds), and whether the instance has triangles (a mesh without any has an infinite
    box). `mesh_bounds`: (meshes, 2, 3) float32 object boxes."""
    box = mesh_bounds[mesh_ids].astype(np.float64)  # (I, 2, 3)
    valid = np.isfinite(box).all(axis=(1, 2))
    box = np.where(valid[:, None, None], box, 0.0)
    corners = np.stack([np.stack([box[:, (k >> a) & 1, a] for a in range(3)], axis=1)
                        for k in range(8)], axis=1)  # (I, 8, 3)
    world = np.einsum("nij,nkj->nki", frames["lin"], corners) + frames["trans"][:, None, :]
    lo, hi = world.min(axis=1), world.max(axis=1)
    reach = np.maximum(np.abs(lo - frames["trans"]), np.abs(hi - frames["trans"])).max(axis=1)
    pad = SAFETY * UNIT * frames["cond"] * reach * (1.0 + 1e-6)
    plo, phi = round_out(lo - pad[:, None], hi + pad[:, None])
    ulo, uhi = round_out(lo, hi)
    return plo, phi, np.stack([ulo, uhi], axis=1), valid


def slope(frames: dict) -> float:
    """How far per unit t, per unit ||d||_inf, the top level's walls move out (module doc):
    SAFETY times 3 u C over the instances (2 u C for the rays' rounding, u C for t's)."""
    cond = float(frames["cond"].max()) if len(frames["cond"]) else 1.0
    return SAFETY * 3.0 * UNIT * cond
