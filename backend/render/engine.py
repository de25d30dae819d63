"""The engine as the service meets it: loaded before the first request, its versions and
devices, a device checked by name, the optional denoiser, an upload's zero-area triangles.

Every function imports the engine when called, so that importing the service (and
`scenesort --help`) does not pay for Warp.
"""

from __future__ import annotations

import importlib
import logging

import numpy as np

log = logging.getLogger("scenesort.engine")


def load() -> None:
    """Import the engine (Warp and its kernel modules' Python side)."""
    importlib.import_module("scenesort.kernels")


def warm_up(device: str) -> None:
    """Build and render a one-triangle scene so that Warp loads (or compiles) every kernel
    module now; a failure is logged and left for real requests to report."""
    try:
        from scenesort import kernels

        vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
        bvh = kernels.build_bvh(vertices, np.array([[0, 1, 2]], np.int32), device=device)
        rays = np.array([[0.2, 0.2, 1.0]], np.float32), np.array([[0, 0, -1]], np.float32)
        kernels.render_ao(bvh, *rays, spp=1)
        if device == "cpu":  # the host helpers' module (threads start on first use)
            import warp as wp
            from scenesort.kernels.core import helpers

            wp.load_module(helpers.serve_kernel.module, device="cpu")
    except Exception:  # noqa: BLE001 - never stop the service over a warm-up
        log.exception("warm-up on %s failed", device)


def warp_version() -> str:
    import warp

    return warp.config.version


def devices() -> list[str]:
    """Every Warp device here ("cpu", "cuda:0", ...)."""
    import warp

    return [str(d) for d in warp.get_devices()]


def device_problem(device: str) -> str | None:
    """None if Warp has `device`, else a message listing the devices it has."""
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING  # no greeting: stdout is for the 'serving on' line
    wp.init()
    try:
        wp.get_device(device)
    except (RuntimeError, ValueError):
        return f"--device {device!r} is not available here; this machine has {devices()}"
    return None


def denoiser_problem() -> str | None:
    """Why this install cannot denoise (the message names the extra to install), or None."""
    from scenesort.kernels.render.denoise import DenoiserMissing, require_denoiser

    try:
        require_denoiser()
    except DenoiserMissing as exc:
        return str(exc)
    return None


def denoise_extra() -> str:
    """The pip command that installs the denoiser."""
    from scenesort.kernels.render.denoise import EXTRA_HINT

    return EXTRA_HINT


def count_degenerate(vertices: np.ndarray, indices: np.ndarray) -> int:
    """Zero-area triangles (kept, never hit), by the engine's own test on every core."""
    from scenesort.kernels.core import count_degenerate as engine_count

    return engine_count(vertices, indices, device="cpu")
