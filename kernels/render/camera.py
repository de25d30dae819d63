"""Blender's camera model (pinhole and orthographic) as primary rays, numpy only.

The model follows Blender/Cycles exactly (checked against bpy 5.0.1 in
tests/kernels/test_camera.py):

- the camera looks along its local -Z with +Y up; the columns of the 3x3 part of
  `matrix_world` are normalised first (Cycles drops object scale the same way);
- `sensor_fit` AUTO fits the wider image side with `sensor_width` (so a portrait
  image spreads `sensor_width` across y), HORIZONTAL puts `sensor_width` across x,
  VERTICAL puts `sensor_height` across y;
- with `s = sensor / lens` (perspective) or `s = ortho_scale` (orthographic) and
  `pix = s / (W if the fit is horizontal else H)`, raster point (px, py), counted
  in pixels from the image's top-left corner, lies on the image plane at
  `x = (px - W/2) * pix + shift_x * s`, `y = (H/2 - py) * pix + shift_y * s`;
- pixel (row r, column c) samples its centre (c + 0.5, r + 0.5); row 0 is the
  TOP of the image (Blender's raster y counts from the bottom, and
  `bpy.types.Image.pixels` store the bottom row first: flip before writing);
- clipping as Cycles does it: perspective clip planes are camera-space depths,
  so a ray's `tmin = clip_start / cos` and `tmax = clip_end / cos` where cos is
  the angle to the view axis; orthographic rays start on the image plane
  through the camera and use `tmin = clip_start`, `tmax = clip_end`.

Wire form (`to_dict` / `from_dict`, used by the HTTP service and the add-on):
a JSON object with exactly the dataclass fields; `matrix_world` is a list of
four rows of four numbers (Blender's `Object.matrix_world`, row-major).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import MISSING, dataclass, field, fields
from typing import Any, Literal

import numpy as np

CameraType = Literal["PERSP", "ORTHO"]
SensorFit = Literal["AUTO", "HORIZONTAL", "VERTICAL"]

CAMERA_TYPES: tuple[str, ...] = ("PERSP", "ORTHO")
SENSOR_FITS: tuple[str, ...] = ("AUTO", "HORIZONTAL", "VERTICAL")
MAX_RESOLUTION = 65536  # Blender's limit for resolution_x / resolution_y
MAX_BLADES = 16  # Blender's limit for CameraDOFSettings.aperture_blades


def _finite(name: str, value: Any) -> float:
    """A float from a real number, or a ValueError naming the field."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise ValueError(f"camera.{name} must be a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"camera.{name} must be finite, got {value!r}")
    return value


def _positive(name: str, value: Any) -> float:
    value = _finite(name, value)
    if value <= 0.0:
        raise ValueError(f"camera.{name} must be > 0, got {value!r}")
    return value


def _resolution(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise ValueError(f"camera.{name} must be an integer pixel count, got {value!r}")
    if not 1 <= int(value) <= MAX_RESOLUTION:
        raise ValueError(f"camera.{name} must be in 1..{MAX_RESOLUTION}, got {value!r}")
    return int(value)


def _matrix(value: Any) -> tuple[tuple[float, ...], ...]:
    """Validate a 4x4 affine camera-to-world matrix; return it as nested tuples."""
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"camera.matrix_world must be a 4x4 array of numbers: {exc}") from None
    if m.shape != (4, 4):
        raise ValueError(f"camera.matrix_world must have shape (4, 4), got {m.shape}")
    if not np.all(np.isfinite(m)):
        raise ValueError("camera.matrix_world must be finite (no NaN or Inf)")
    if not np.allclose(m[3], (0.0, 0.0, 0.0, 1.0), atol=1e-6):
        raise ValueError(
            f"camera.matrix_world must be affine with last row (0, 0, 0, 1), got {m[3].tolist()}"
        )
    norms = np.linalg.norm(m[:3, :3], axis=0)
    if np.any(norms < 1e-12):
        raise ValueError("camera.matrix_world has a zero-length axis (a column of its 3x3 part)")
    if abs(np.linalg.det(m[:3, :3] / norms)) < 1e-6:
        raise ValueError("camera.matrix_world is singular: its axes must span 3D space")
    return tuple(tuple(float(x) for x in row) for row in m)


def rotated(points: np.ndarray, r: np.ndarray) -> np.ndarray:
    """points @ r.T for (N, 3) points, without BLAS: after a BLAS product this large
    OpenBLAS's threads spin on, taking a core from what runs next (a job's Z-pass trace of
    76,800 rays right after Camera.rays took 26 ms against 13 ms)."""
    return points[:, :1] * r[:, 0] + points[:, 1:2] * r[:, 1] + points[:, 2:3] * r[:, 2]


@dataclass(frozen=True)
class Camera:
    """A Blender camera: placement, final resolution and lens; see the module docstring.

    Defaults are those of `bpy.data.cameras.new()` in Blender 5.0.
    `clip_start` may be 0 here (Blender's own minimum is 1e-6).
    """

    matrix_world: tuple[tuple[float, ...], ...]  # 4x4 camera-to-world, row-major
    width: int  # final pixels across (resolution_x * percentage / 100)
    height: int  # final pixels down
    type: CameraType = "PERSP"
    lens: float = 50.0  # focal length, mm (PERSP only)
    sensor_width: float = 36.0  # mm
    sensor_height: float = 24.0  # mm
    sensor_fit: SensorFit = "AUTO"
    ortho_scale: float = 6.0  # world units across the fitted side (ORTHO only)
    shift_x: float = 0.0  # fraction of the fitted side
    shift_y: float = 0.0
    clip_start: float = 0.1  # camera-space depth
    clip_end: float = 1000.0
    # Depth of field, as Cycles' camera has it (rendered by the filtered film,
    # kernels/render/filtered.py): the lens's radius in world units (Cycles' aperturesize:
    # lens * 1e-3 / (2 * f-stop) from Blender's f-stop for PERSP, 1 / (2 * f-stop) for
    # ORTHO; 0: a pinhole), the camera-space
    # depth in focus, and the aperture's shape (0 blades: round, else a regular polygon of
    # that many corners turned by `aperture_rotation` radians, squeezed across x by
    # `aperture_ratio` as an anamorphic lens).
    aperture_size: float = 0.0
    focus_distance: float = 10.0
    aperture_blades: int = 0
    aperture_rotation: float = 0.0
    aperture_ratio: float = 1.0
    _r: np.ndarray = field(init=False, repr=False, compare=False)  # normalised rotation part

    def __post_init__(self) -> None:
        set_ = object.__setattr__  # frozen: normalise fields once, here
        set_(self, "matrix_world", _matrix(self.matrix_world))
        set_(self, "width", _resolution("width", self.width))
        set_(self, "height", _resolution("height", self.height))
        if self.type not in CAMERA_TYPES:
            raise ValueError(f"camera.type must be one of {CAMERA_TYPES}, got {self.type!r}")
        if self.sensor_fit not in SENSOR_FITS:
            raise ValueError(
                f"camera.sensor_fit must be one of {SENSOR_FITS}, got {self.sensor_fit!r}"
            )
        for name in ("lens", "sensor_width", "sensor_height", "ortho_scale"):
            set_(self, name, _positive(name, getattr(self, name)))
        for name in ("shift_x", "shift_y", "clip_start", "clip_end"):
            set_(self, name, _finite(name, getattr(self, name)))
        for name in ("aperture_size", "aperture_rotation"):
            set_(self, name, _finite(name, getattr(self, name)))
        for name in ("focus_distance", "aperture_ratio"):
            set_(self, name, _positive(name, getattr(self, name)))
        if self.aperture_size < 0.0:
            raise ValueError(f"camera.aperture_size must be >= 0 (0: no depth of field), got "
                             f"{self.aperture_size!r}")
        blades = self.aperture_blades
        if isinstance(blades, bool) or not isinstance(blades, int | np.integer) or not (
                blades == 0 or 3 <= blades <= MAX_BLADES):
            raise ValueError(f"camera.aperture_blades must be 0 (round) or an integer in "
                             f"3..{MAX_BLADES}, got {blades!r}")
        set_(self, "aperture_blades", int(blades))
        if self.clip_start < 0.0:
            raise ValueError(f"camera.clip_start must be >= 0, got {self.clip_start!r}")
        if self.clip_end <= self.clip_start:
            raise ValueError(
                f"camera.clip_end ({self.clip_end!r}) must be greater than "
                f"camera.clip_start ({self.clip_start!r})"
            )
        m = np.array(self.matrix_world)
        set_(self, "_r", m[:3, :3] / np.linalg.norm(m[:3, :3], axis=0))

    # --- geometry -----------------------------------------------------------------

    @property
    def position(self) -> np.ndarray:
        """The camera's world position (float64, (3,))."""
        return np.array(self.matrix_world)[:3, 3]

    @property
    def rotation(self) -> np.ndarray:
        """The 3x3 part of matrix_world with its columns normalised (float64)."""
        return self._r.copy()

    @property
    def forward(self) -> np.ndarray:
        """Unit view direction in world space: the camera's local -Z."""
        f = -self._r[:, 2]
        return f / np.linalg.norm(f)

    @property
    def horizontal_fit(self) -> bool:
        """Whether the sensor spans the image's width (else its height)."""
        if self.sensor_fit == "AUTO":
            return self.width >= self.height
        return self.sensor_fit == "HORIZONTAL"

    def plane_scale(self) -> float:
        """`s`: image-plane extent of the fitted side (at depth 1 for PERSP)."""
        if self.type == "ORTHO":
            return self.ortho_scale
        # AUTO uses sensor_width whichever side it fits (BKE_camera_sensor_size).
        sensor = self.sensor_height if self.sensor_fit == "VERTICAL" else self.sensor_width
        return sensor / self.lens

    def raster_plane(self) -> tuple[tuple[float, float], ...]:
        """The raster -> image-plane map, one affine map per axis, as (centre, step,
        offset) pairs (x, y): plane = (raster - centre) * step + offset. The one
        definition of where a raster point lies, for `raster_to_camera` and the device's
        camera rays (filtered.py); a subclass that frames the image otherwise (a window,
        non-square pixels: backend/render/framing.py) overrides this alone."""
        s = self.plane_scale()
        pix = s / (self.width if self.horizontal_fit else self.height)
        # y: (H/2 - py) * pix, written as (py - H/2) * -pix (the same float64 numbers)
        return ((0.5 * self.width, 0.5 * self.height), (pix, -pix),
                (self.shift_x * s, self.shift_y * s))

    def raster_to_camera(self, px: np.ndarray, py: np.ndarray) -> np.ndarray:
        """Camera-space image-plane points (float64, (N,3)) for raster coordinates.

        `px`, `py` are pixels from the image's left and top edges (pixel centres at
        +0.5). PERSP points lie at depth 1 (z = -1), ORTHO points at z = 0.
        """
        px = np.asarray(px, dtype=np.float64).ravel()
        py = np.asarray(py, dtype=np.float64).ravel()
        centre, step, offset = self.raster_plane()
        pts = np.empty((px.size, 3), dtype=np.float64)
        pts[:, 0] = (px - centre[0]) * step[0] + offset[0]
        pts[:, 1] = (py - centre[1]) * step[1] + offset[1]
        pts[:, 2] = -1.0 if self.type == "PERSP" else 0.0
        return pts

    def rays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """One ray per pixel centre, row-major with row 0 at the top.

        Returns origins (H*W,3), unit directions (H*W,3), tmin (H*W,) and tmax (H*W,),
        all float32 (computed in float64, then cast). Ray i is pixel
        (row i // width, column i % width).
        """
        rows, cols = np.divmod(np.arange(self.width * self.height, dtype=np.int64), self.width)
        pts = self.raster_to_camera(cols + 0.5, rows + 0.5)
        m = np.array(self.matrix_world)
        t = m[:3, 3]
        if self.type == "PERSP":
            world = rotated(pts, self._r)
            length = np.linalg.norm(world, axis=1)
            directions = world / length[:, None]
            origins = np.broadcast_to(t, directions.shape)
            # A point at ray parameter t has camera-space depth t / length.
            tmin = self.clip_start * length
            tmax = self.clip_end * length
        else:
            origins = t + rotated(pts, self._r)
            d = -self._r[:, 2]
            directions = np.broadcast_to(d / np.linalg.norm(d), origins.shape)
            tmin = np.full(origins.shape[0], self.clip_start)
            tmax = np.full(origins.shape[0], self.clip_end)
        return (
            np.ascontiguousarray(origins, dtype=np.float32),
            np.ascontiguousarray(directions, dtype=np.float32),
            tmin.astype(np.float32),
            tmax.astype(np.float32),
        )

    # --- construction -------------------------------------------------------------

    @classmethod
    def look_at(
        cls,
        position: Any,
        target: Any,
        up: Any,
        fov_y_deg: float,
        width: int,
        height: int,
        clip_start: float = 0.0,
        clip_end: float = 1e10,
    ) -> Camera:
        """A pinhole camera at `position` looking at `target` with a vertical field of view.

        This is the form of the cameras in scenes.json. The fit is VERTICAL, so a wider
        image widens the horizontal view and keeps `fov_y_deg`. The default clip range
        is effectively unclipped (scenes.json cameras have none).
        """
        pos = np.asarray(position, dtype=np.float64)
        tgt = np.asarray(target, dtype=np.float64)
        upv = np.asarray(up, dtype=np.float64)
        for name, v in (("position", pos), ("target", tgt), ("up", upv)):
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise ValueError(f"look_at {name} must be 3 finite numbers, got {v.tolist()}")
        fov = _finite("fov_y_deg", fov_y_deg)
        if not 0.0 < fov < 180.0:
            raise ValueError(f"camera.fov_y_deg must be in (0, 180), got {fov!r}")
        fwd = tgt - pos
        if np.linalg.norm(fwd) == 0.0:
            raise ValueError("look_at position and target must differ")
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, upv)
        if np.linalg.norm(right) < 1e-9 * max(np.linalg.norm(upv), 1e-300):
            raise ValueError("look_at up must not be parallel to (target - position)")
        right /= np.linalg.norm(right)
        true_up = np.cross(right, fwd)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, true_up, -fwd, pos
        sensor_height = 24.0
        lens = 0.5 * sensor_height / math.tan(math.radians(fov) / 2.0)
        return cls(
            matrix_world=m,
            width=width,
            height=height,
            lens=lens,
            sensor_height=sensor_height,
            sensor_fit="VERTICAL",
            clip_start=clip_start,
            clip_end=clip_end,
        )

    def to_dict(self) -> dict[str, Any]:
        """The JSON-able wire form: every field, matrix_world as 4 rows of 4 floats."""
        out = {f.name: getattr(self, f.name) for f in fields(self) if f.init}
        out["matrix_world"] = [list(row) for row in self.matrix_world]
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Camera:
        """Parse the wire form; unknown or missing keys raise ValueError naming them."""
        if not isinstance(data, Mapping):
            raise ValueError(f"camera must be a JSON object, got {type(data).__name__}")
        valid = [f.name for f in fields(cls) if f.init]
        unknown = sorted(set(data) - set(valid))
        if unknown:
            raise ValueError(f"camera has unknown keys {unknown}; valid keys are {valid}")
        required = [f.name for f in fields(cls) if f.init and f.default is MISSING]
        missing = [name for name in required if name not in data]
        if missing:
            raise ValueError(f"camera is missing required keys {missing}")
        return cls(**dict(data))
