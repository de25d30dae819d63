"""What a request is refused before any work starts: ray casts over the service's budget
(--max-work), denoising where the denoiser is not installed, an engine the scene cannot
use, an image of too many pixels; each a 422 naming the parameter. (AO settings the engine
would refuse are refused as AoOptions are made: AoSettings.options().)"""

from __future__ import annotations

from typing import Any

from scenesort.backend.render import engine
from scenesort.backend.wire import binary as wire
from scenesort.backend.wire.problems import ApiError

from scenesort.ao_options import AoOptions

MAX_JOB_PIXELS = 4096 * 4096


def check_work(max_work: int, count: int, count_name: str, options: AoOptions) -> None:
    """Refuse a request whose ray casts (count x samples per ray) exceed --max-work."""
    per_ray = options.max_spp if options.adaptive else options.spp
    spp_name = "the adaptive cap of spp" if options.adaptive else "spp"
    work = count * per_ray
    if work > max_work:
        raise ApiError(
            422, f"{count_name}, spp",
            f"{count_name} x {spp_name} = {count} x {per_ray} = {work} ray casts, over this "
            f"service's budget of {max_work} (serve --max-work)",
            f"lower {count_name} or spp so that their product is at most {max_work}"
            ", split the work into several requests, or start the service with a larger "
            "--max-work",
            "over_budget",
        )


def check_denoiser(options: AoOptions) -> None:
    """Refuse denoising where the denoiser is not installed, naming the extra."""
    problem = engine.denoiser_problem() if options.denoise else None
    if problem is not None:
        raise ApiError(
            422, "denoise", f"this service cannot denoise: {problem}",
            f"install the extra where the service runs ({engine.denoise_extra()}) and "
            "restart it, or send denoise=false",
            "denoiser_missing",
        )


def check_engine(scene: Any, options: AoOptions) -> None:
    """DACRT traces one flat triangle list: instance lists are for the BVH engine."""
    if options.engine == "dacrt" and isinstance(scene, wire.InstanceScene):
        raise ApiError(
            422, "engine", "engine dacrt traces single-mesh scenes; this is an instance list",
            "use engine bvh for instance lists, or upload the flattened scene with "
            "POST /v1/scenes for dacrt",
            "invalid_parameter",
        )


def check_pixels(width: int, height: int) -> None:
    """Refuse a job image larger than MAX_JOB_PIXELS."""
    if width * height > MAX_JOB_PIXELS:
        raise ApiError(
            422,
            "camera.width",
            f"{width}x{height} is more than {MAX_JOB_PIXELS} pixels",
            "render a smaller image or tiles",
            "too_many_pixels",
        )
