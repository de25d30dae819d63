"""What a request is refused before any work starts: ray casts over the service's budget
(--max-work), AO settings the engine would refuse, an engine the scene cannot use, an
image of too many pixels; each a 422 naming the parameter."""

from __future__ import annotations

from typing import Any

from scenesort.backend.render import engine
from scenesort.backend.render.ao import AoParams
from scenesort.backend.wire import binary as wire
from scenesort.backend.wire.problems import ApiError

MAX_JOB_PIXELS = 4096 * 4096


def check_work(max_work: int, count: int, count_name: str, params: AoParams) -> None:
    """Refuse a request whose ray casts (count x samples per ray) exceed --max-work."""
    per_ray = engine.adaptive_max_spp() if params.adaptive else params.spp
    spp_name = "the adaptive cap of spp" if params.adaptive else "spp"
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


def check_ao(params: AoParams) -> None:
    """Refuse what the engine would refuse, naming the query parameter."""
    max_spp = engine.adaptive_max_spp()
    if params.adaptive and params.spp > max_spp:
        raise ApiError(
            422,
            "spp",
            f"with target_error or max_pixel_error, spp is the minimum per ray and must be "
            f"<= {max_spp}, got {params.spp}",
            f"lower spp to at most {max_spp}, or drop target_error and max_pixel_error for "
            "a fixed spp",
            "invalid_parameter",
        )
    problem = engine.denoiser_problem() if params.denoise else None
    if problem is not None:
        raise ApiError(
            422, "denoise", f"this service cannot denoise: {problem}",
            f"install the extra where the service runs ({engine.denoise_extra()}) and "
            "restart it, or send denoise=false",
            "denoiser_missing",
        )


def check_engine(scene: Any, params: AoParams) -> None:
    """DACRT traces one flat triangle list: instance lists are for the BVH engine."""
    if params.engine == "dacrt" and isinstance(scene, wire.InstanceScene):
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
