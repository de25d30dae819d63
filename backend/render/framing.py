"""A camera job's film: a window of the frame (Blender's border render) and non-square
pixels (Blender's pixel aspect), on top of `kernels.Camera`'s model.

`kernels.Camera` renders the whole frame with square pixels. `FramedCamera` keeps its
lens, placement and clip planes and changes only where the pixel centres lie: its
`width` and `height` are the window's (one ray per window pixel), the frame's size is
`frame_width` x `frame_height`, and the window starts `x0` pixels from the frame's left
edge and `y0` from its top. Blender's viewplane (BKE_camera_params_compute_viewplane):
a pixel is `pix` wide and `ycor * pix` tall, `ycor = pixel_aspect_y / pixel_aspect_x`;
AUTO fits the width when `frame_width >= ycor * frame_height`; `pix = s / frame_width`
(width fitted) or `s / (ycor * frame_height)`; the lens shift is not scaled by `ycor`.
With the whole frame and `ycor = 1` the rays equal `kernels.Camera`'s bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scenesort.kernels import Camera


@dataclass(frozen=True)
class FramedCamera(Camera):
    """`Camera` rendering the window (x0, y0, width, height) of a frame with pixels
    `ycor` times as tall as wide."""

    frame_width: int = 0  # 0: the window is the whole frame
    frame_height: int = 0
    x0: int = 0
    y0: int = 0
    ycor: float = 1.0

    def __post_init__(self) -> None:
        super().__post_init__()
        set_ = object.__setattr__
        set_(self, "frame_width", int(self.frame_width) or self.width)
        set_(self, "frame_height", int(self.frame_height) or self.height)
        if not (
            0 <= self.x0 <= self.frame_width - self.width
            and 0 <= self.y0 <= self.frame_height - self.height
        ):
            raise ValueError(
                f"the window {self.width}x{self.height} at ({self.x0}, {self.y0}) does not "
                f"fit in the {self.frame_width}x{self.frame_height} frame"
            )
        if not (np.isfinite(self.ycor) and self.ycor > 0):
            raise ValueError(f"the pixel aspect must be finite and > 0, got {self.ycor!r}")

    @property
    def horizontal_fit(self) -> bool:
        if self.sensor_fit == "AUTO":
            return self.frame_width >= self.ycor * self.frame_height
        return self.sensor_fit == "HORIZONTAL"

    def raster_plane(self) -> tuple[tuple[float, float], ...]:
        """`Camera.raster_plane` with raster coordinates counted in the window."""
        s = self.plane_scale()
        w, h = self.frame_width, self.frame_height
        pix = s / (w if self.horizontal_fit else self.ycor * h)
        # (px + x0 - w/2) * pix and (h/2 - py - y0) * pix * ycor, as Camera writes them
        return ((0.5 * w - self.x0, 0.5 * h - self.y0), (pix, -(pix * self.ycor)),
                (self.shift_x * s, self.shift_y * s))


def framed(
    camera: dict[str, Any], window: dict[str, int] | None, pixel_aspect: tuple[float, float]
) -> FramedCamera:
    """The job's camera: `camera` (the wire form) rendering `window` ({x, y, width,
    height} from the frame's top-left; None: the whole frame) with `pixel_aspect` (x, y)."""
    frame = {"frame_width": camera["width"], "frame_height": camera["height"]}
    if window is not None:
        frame |= {"x0": window["x"], "y0": window["y"]}
        camera = {**camera, "width": window["width"], "height": window["height"]}
    return FramedCamera(**camera, **frame, ycor=pixel_aspect[1] / pixel_aspect[0])
