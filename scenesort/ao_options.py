"""Every setting of an AO render: one frozen dataclass, `AoOptions`, each field defined,
documented, bounded and checked here once.

The engine renders with it (`scenesort.kernels.render_ao`, which re-exports it as
`kernels.AoOptions`); the service's request models, the command line, frame bundles and the
add-on's properties take their defaults, ranges, choices and documentation from its bounds
as data (`AO_OPTIONS`: name -> `OptionSpec`, in field order) rather than writing them again.
This module imports numpy only, never Warp or the engine: the service's wire layer, which
must not import the engine, reads it too (docs/architecture.md). In the documentation
"unset" is None in Python, null or absent in JSON, an option not given on the command line.
"""

from __future__ import annotations

import types
import typing
from dataclasses import dataclass, field, fields, replace
from typing import Any, Literal

import numpy as np

Sampler = Literal["sobol", "random"]
Engine = Literal["bvh", "dacrt"]
PixelFilter = Literal["BOX", "GAUSSIAN", "BLACKMAN_HARRIS"]  # Cycles' pixel_filter_type names
PIXEL_FILTERS: tuple[str, ...] = typing.get_args(PixelFilter)
MAX_FILTER_WIDTH = 10.0  # Blender's limit for scene.cycles.filter_width, in pixels
# A filter at most this wide (px) renders pixel centres: its samples would land within 1/20
# of a pixel of the centre (Cycles' narrowest, 0.01 px, is how it renders without a filter)
# while each would trace a camera ray of its own, doubling a render's work.
CENTRE_FILTER_WIDTH = 0.05
DEFAULT_MAX_SPP = 1024
MIN_ADAPTIVE_SPP = 8  # fewest samples before a pixel's variance is trusted (measured: 4-16)
DEFAULT_TERMINATOR_OFFSET = 0.1  # Blender's Object.shadow_terminator_geometry_offset default
DISTANCE_FRACTION = 0.1  # distance unset: this fraction of the scene box's diagonal
SERVICE_MAX_SPP = 4096  # the most samples per pixel a service request or the add-on offers
SEED_MAX = 2**31 - 1  # the sampler's key is an int32


class OptionError(ValueError):
    """A value an AO setting does not take: `name` is the setting at fault, the message
    says what is wrong and `fix` what to change."""

    def __init__(self, name: str, message: str, fix: str) -> None:
        super().__init__(message)
        self.name = name
        self.fix = fix

    def __reduce__(self) -> tuple[Any, ...]:  # pickled with its fields (Ray ships errors)
        return type(self), (self.name, str(self), self.fix)


@dataclass(frozen=True)
class OptionSpec:
    """What one setting takes: `kind` (int, float, str or bool) within [low, high] (an end
    excluded where `low_open` / `high_open`; None: unbounded) or one of `choices`; None
    too where `optional`. `soft_high`: the most a service request or a UI offers, where
    the engine takes more."""

    name: str
    kind: type
    default: Any
    doc: str
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    choices: tuple[str, ...] | None = None
    optional: bool = False
    soft_high: float | None = None

    def check(self, value: Any) -> Any:
        """The value as the kind (numpy scalars become Python's), or ValueError naming the
        setting and what it takes."""
        if value is None:
            if self.optional:
                return None
            raise self.error(None)
        if self.kind is bool:
            if isinstance(value, bool | np.bool_):
                return bool(value)
        elif self.kind is str:
            if value in self.choices:
                return str(value)
        else:
            numbers = (int, np.integer) if self.kind is int else (int, float, np.number)
            if isinstance(value, numbers) and not isinstance(value, bool | np.bool_):
                number = self.kind(value)
                if self.within(number):
                    return number
        raise self.error(value)

    def error(self, value: Any) -> OptionError:
        """The OptionError of `value`, which this setting does not take."""
        return OptionError(self.name, f"{self.name} must be {self.takes()}, got {value!r}",
                           f"set {self.name} to {self.takes()}")

    def within(self, x: Any) -> Any:
        """Whether the number x lies in the range (NaN never does); of an array, per
        element."""
        x = np.asarray(x, dtype=np.float64)
        ok = ~np.isnan(x)
        if self.low is not None:
            ok &= x > self.low if self.low_open else x >= self.low
        if self.high is not None:
            ok &= x < self.high if self.high_open else x <= self.high
        return ok

    def takes(self) -> str:
        """The values it takes, in words: 'an integer >= 1', 'a number in (0, 1) or None'."""
        if self.kind is bool:
            text = "True or False"
        elif self.kind is str:
            text = f"one of {list(self.choices)}"
        else:
            text = " ".join(filter(None, ("an integer" if self.kind is int else "a number",
                                          self.range())))
        return text + (" or None" if self.optional else "")

    def range(self) -> str:
        """The range in words: 'in [0, 1]', 'in (0, 1)', '> 0', '>= 1' ('' if unbounded)."""
        if self.low is not None and self.high is not None:
            return (f"in {'(' if self.low_open else '['}{_plain(self.low)}, "
                    f"{_plain(self.high)}{')' if self.high_open else ']'}")
        if self.low is not None:
            return f"{'>' if self.low_open else '>='} {_plain(self.low)}"
        if self.high is not None:
            return f"{'<' if self.high_open else '<='} {_plain(self.high)}"
        return ""


def _plain(x: float) -> str:
    """A bound as written: 1 and 0 without a decimal point, 2147483647 in full."""
    return str(int(x)) if x == int(x) else str(x)


def _option(default: Any, doc: str, **bounds: Any) -> Any:
    """A field of AoOptions with its documentation and bounds (OptionSpec's fields)."""
    return field(default=default, metadata={"doc": doc, "bounds": bounds})


@dataclass(frozen=True)
class AoOptions:
    """How an AO render samples and traces (`render_ao`; kernels/render/ao.py defines AO).
    Checked when made: a bad value raises OptionError (a ValueError) naming the field."""

    spp: int = _option(
        16, "samples per hit pixel; with an error target, the fewest per pixel (at least "
        f"{MIN_ADAPTIVE_SPP})", low=1, soft_high=SERVICE_MAX_SPP)
    distance: float | None = _option(
        None, "occluders farther than this from the shaded point are ignored (unset: "
        f"{DISTANCE_FRACTION} of the scene box's diagonal)", low=0.0, low_open=True)
    seed: int = _option(0, "the samples' seed: each sample is a pure function of (seed, "
                        "ray, sample index)", low=0, high=SEED_MAX)
    target_error: float | None = _option(
        None, "stop once the image's estimated RMSE over hit pixels against the converged "
        "AO (AO in [0, 1]) is safely below this: the achieved RMSE is within [0.7, 1.0] x "
        "it in >= 95% of renders (unset: a fixed spp)",
        low=0.0, high=1.0, low_open=True, high_open=True)
    max_pixel_error: float | None = _option(
        None, "stop each pixel once its 95% confidence half-width is below this: every "
        "pixel bounded, at more samples than target_error for the same number (unset: no "
        "bound)", low=0.0, high=1.0, low_open=True, high_open=True)
    max_spp: int = _option(
        DEFAULT_MAX_SPP, "with an error target, the most samples per pixel", low=1)
    sampler: Sampler = _option(
        "sobol", "Owen-scrambled Sobol, or independent random samples: both unbiased")
    engine: Engine = _option(
        "bvh", "what traces the rays: the BVH (of a mesh or a two-level scene), or the "
        "task-pool DACRT over a mesh BVH's triangles (the same AO to float32 rounding)")
    terminator_offset: float = _option(
        DEFAULT_TERMINATOR_OFFSET, "Cycles' shadow terminator geometry offset: how far "
        "smooth triangles lift occlusion rays off their flat surface (render_ao takes one "
        "per triangle or instance)", low=0.0, high=1.0)
    pixel_filter: PixelFilter = _option(
        "BLACKMAN_HARRIS", "a camera render's pixel filter (Cycles' Film > Pixel Filter; its "
        "default Blackman-Harris), used where filter_width > 0")
    filter_width: float = _option(
        0.0, "a camera render's pixel filter width in pixels (Cycles' default 1.5): each "
        "sample traces its own camera ray from a sub-pixel position drawn from the filter, "
        "so edges and alpha are anti-aliased as Cycles renders them; 0: one camera ray "
        "through each pixel's centre, coverage 0 or 1, as for a width up to 0.05 px. Filtered "
        "renders take engine bvh and no denoising; otherwise they render pixel centres "
        "(film_fallback)",
        low=0.0, high=MAX_FILTER_WIDTH)
    denoise: bool = _option(
        False, "denoise the image with Intel Open Image Denoise, the shading normals as its "
        'guide (needs pip install "scenesort[denoise]"); the estimated RMSE stays the raw '
        "render's")
    threads: int | None = _option(
        None, "CPU host threads (unset: every core); the result does not depend on it",
        low=1)

    def __post_init__(self) -> None:
        for spec in AO_OPTIONS.values():
            object.__setattr__(self, spec.name, spec.check(getattr(self, spec.name)))
        if self.adaptive and self.max_spp < self.min_spp:
            raise self._over_max_spp()

    def _over_max_spp(self) -> OptionError:
        """With an error target, more samples than max_spp asked for: of spp (over it) or
        of max_spp (below MIN_ADAPTIVE_SPP)."""
        if self.spp > self.max_spp:
            return OptionError(
                "spp", f"with target_error or max_pixel_error, spp is the fewest samples per "
                f"pixel and must be <= max_spp ({self.max_spp}), got {self.spp}",
                f"lower spp to at most {self.max_spp}, or drop target_error and "
                "max_pixel_error for a fixed spp")
        return OptionError(
            "max_spp", f"with target_error or max_pixel_error, max_spp must be >= "
            f"{MIN_ADAPTIVE_SPP} (the fewest samples per pixel), got {self.max_spp}",
            f"raise max_spp to at least {MIN_ADAPTIVE_SPP}")

    @property
    def adaptive(self) -> bool:
        """Whether an error target decides the samples (else `spp` per pixel)."""
        return self.target_error is not None or self.max_pixel_error is not None

    @property
    def film_fallback(self) -> str | None:
        """Why a camera render with filter_width > 0 renders pixel centres instead (None:
        it filters, or filter_width is 0). Each sample of a filtered render traces its own
        camera ray; the denoiser's guides and DACRT's ray batches work on one primary hit
        per pixel."""
        if self.filter_width == 0.0:
            return None
        if self.filter_width <= CENTRE_FILTER_WIDTH:
            return (f"pixel centres: a {self.filter_width:g} px filter's samples would all "
                    "land within 1/20 px of them")
        reasons = [reason for reason, applies in (
            ("denoise", self.denoise), ("engine dacrt", self.engine == "dacrt")) if applies]
        if not reasons:
            return None
        return (f"pixel centres: {' and '.join(reasons)} renders one camera ray per pixel "
                "centre (the pixel filter needs engine bvh and no denoising)")

    @property
    def filtered(self) -> bool:
        """Whether a camera render goes through the pixel filter (filter_width > 0 and no
        `film_fallback`)."""
        return self.filter_width > 0.0 and self.film_fallback is None

    @property
    def film(self) -> str:
        """What a camera render's pixels are, in words (the service job's `film`):
        "BLACKMAN_HARRIS 1.5 px", "pixel centres", or the `film_fallback`."""
        if self.filtered:
            return f"{self.pixel_filter} {self.filter_width:g} px"
        return self.film_fallback or "pixel centres"

    @property
    def min_spp(self) -> int:
        """Samples every hit pixel gets: spp, at least MIN_ADAPTIVE_SPP when adaptive."""
        return max(self.spp, MIN_ADAPTIVE_SPP) if self.adaptive else self.spp

    def with_(self, **changes: Any) -> AoOptions:
        """A copy with these fields changed (None included: it means what it means for the
        field); an unknown name raises TypeError naming it."""
        unknown = sorted(set(changes) - set(AO_OPTIONS))
        if unknown:
            raise TypeError(f"unknown AO option(s) {unknown}; the options are "
                            f"{list(AO_OPTIONS)}")
        return replace(self, **changes)


def _specs() -> dict[str, OptionSpec]:
    """AO_OPTIONS from AoOptions' annotations (`X | None`: optional; a Literal: choices)
    and its fields' metadata."""
    hints = typing.get_type_hints(AoOptions)
    out = {}
    for f in fields(AoOptions):
        kind = hints[f.name]
        optional = typing.get_origin(kind) is types.UnionType
        if optional:
            kind = next(k for k in typing.get_args(kind) if k is not type(None))
        choices = typing.get_args(kind) if typing.get_origin(kind) is Literal else None
        out[f.name] = OptionSpec(name=f.name, kind=str if choices else kind,
                                 default=f.default, doc=f.metadata["doc"], choices=choices,
                                 optional=optional, **f.metadata["bounds"])
    return out


AO_OPTIONS: dict[str, OptionSpec] = _specs()
