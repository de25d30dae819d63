"""Optional denoising of an AO image with Intel Open Image Denoise (the `scenesort[denoise]`
extra, `pyoidn`): host-side, after the render, never inside a kernel.

OIDN's RT filter is given the AO as grey LDR colour, the primary hits' shading normals (0 on
background) and an albedo of 1 everywhere: AO has no texture, and coverage as the albedo
(0 on background) made the result worse on thin objects (measured at 256x192 against a
4096-spp reference, RMSE at 4/16/64 spp: buddha 0.083/0.042/0.017 with albedo 1 and
0.099/0.050/0.032 with coverage, raw 0.121/0.047/0.018; bunny 0.047/0.023/0.011 against
0.051/0.023/0.013, raw 0.088/0.034/0.012). The auxiliary images are exact (one primary ray
per pixel), so OIDN is told not to prefilter them (`clean_aux`).
Background pixels keep their exact value (AO 1.0) and the output is clipped to [0, 1]:
only hit pixels carry Monte Carlo noise. The denoised image has no error estimate of its
own: a render's `rmse_estimate` is the raw image's (benchmarks/ao_error.py measures the
denoised error against a reference).
"""

from __future__ import annotations

import numpy as np

EXTRA_HINT = 'pip install "scenesort[denoise]"'


class DenoiserMissing(RuntimeError):
    """`pyoidn` is not installed (the `scenesort[denoise]` extra)."""


def require_denoiser() -> None:
    """Raise DenoiserMissing, naming the extra, unless `pyoidn` can be imported."""
    try:
        import pyoidn  # noqa: F401
    except ImportError as exc:
        raise DenoiserMissing(
            f"denoising needs Intel Open Image Denoise: {EXTRA_HINT}"
        ) from exc


def denoise_ao(ao: np.ndarray, normals: np.ndarray, hit: np.ndarray,
               shape: tuple[int, int]) -> np.ndarray:
    """The denoised AO, (R,) float32, of a row-major (height, width) = `shape` image of R
    rays: `ao` (R,), `normals` (R, 3) unit shading normals (0 where missed), `hit` (R,)
    bool. Pixels that missed are returned unchanged."""
    require_denoiser()
    import pyoidn

    h, w = shape
    colour = np.repeat(ao.astype(np.float32).reshape(h, w, 1), 3, axis=2)
    albedo = np.ones_like(colour)
    normal = np.ascontiguousarray(normals.astype(np.float32).reshape(h, w, 3))
    out = pyoidn.denoise(colour, albedo, normal, clean_aux=True)
    grey = np.clip(out.mean(axis=2).reshape(-1), 0.0, 1.0).astype(np.float32)
    return np.where(hit, grey, ao).astype(np.float32)
