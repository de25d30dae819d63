"""Settings (saved with the scene) and runtime status (never saved) of the add-on."""

from __future__ import annotations

import bpy
from bpy.props import (
    BoolProperty,
    CollectionProperty,
    EnumProperty,
    FloatProperty,
    IntProperty,
    PointerProperty,
    StringProperty,
)

from .ao_options import AO_OPTIONS, MIN_ADAPTIVE_SPP

HISTORY_LENGTH = 8  # earlier builds kept for comparison in the panel

# The AO settings' defaults, ranges and choices come from the engine's one definition
# (ao_options.py, generated from scenesort/ao_options.py; docs/addon.md). The settings a
# render may leave unset whose lower end is excluded (target_error, max_pixel_error,
# distance) show that end, 0, for "unset"; an excluded upper end is offered up to a step
# below it.
SPP, SEED, ENGINE = AO_OPTIONS["spp"], AO_OPTIONS["seed"], AO_OPTIONS["engine"]
TARGET_ERROR, MAX_PIXEL_ERROR = AO_OPTIONS["target_error"], AO_OPTIONS["max_pixel_error"]
DISTANCE = AO_OPTIONS["distance"]
OPEN_END_STEP = 0.01
ENGINE_WORDS = {  # the panel's words for each engine the service takes
    "bvh": ("BVH", "Trace AO rays through the built BVH"),
    "dacrt": ("DACRT", "Divide-and-conquer ray tracing (no BVH needed)"),
}
ENGINE_ITEMS = [(name, *ENGINE_WORDS[name]) for name in ENGINE["choices"]]


def _top(spec: dict) -> float:
    """The largest value the panel offers: the upper end, a step below it where excluded."""
    return spec["high"] - OPEN_END_STEP if spec["high_open"] else spec["high"]


class SCENESORT_PG_phase(bpy.types.PropertyGroup):
    """One named phase of a BVH build and its time."""

    name: StringProperty(name="Phase")  # type: ignore[valid-type]
    ms: FloatProperty(name="Milliseconds")  # type: ignore[valid-type]


class SCENESORT_PG_build(bpy.types.PropertyGroup):
    """One earlier build, for the history table."""

    method: StringProperty(name="Method")  # type: ignore[valid-type]
    leaf_size: IntProperty(name="Leaf size")  # type: ignore[valid-type]
    triangles: IntProperty(name="Triangles")  # type: ignore[valid-type]
    total_ms: FloatProperty(name="Total ms")  # type: ignore[valid-type]


class SCENESORT_PG_settings(bpy.types.PropertyGroup):
    """`scene.scenesort`: what to build and render, and the last build's timings.

    The service URL is a preference, not a scene setting: a `server_url` that files
    from older versions carry is never read.
    """

    method: EnumProperty(  # type: ignore[valid-type]
        name="BVH method",
        items=[
            ("sah", "SAH", "32-bin surface area heuristic: slower build, faster rays"),
            ("median", "Median", "Spatial median split: fastest build"),
        ],
        default="sah",
    )
    leaf_size: IntProperty(  # type: ignore[valid-type]
        name="Leaf size",
        description="Most triangles in one BVH leaf (the papers use 8, 16 or 32)",
        default=8,
        min=1,
        max=64,
    )
    spp: IntProperty(  # type: ignore[valid-type]
        name="Samples",
        description=(f"AO rays per pixel (the fewest per pixel, at least {MIN_ADAPTIVE_SPP}, "
                     "with an error target)"),
        default=SPP["default"],
        min=SPP["low"],
        max=SPP["soft_high"],
    )
    target_error: FloatProperty(  # type: ignore[valid-type]
        name="Target error",
        description=(
            "Stop sampling once the image's estimated RMSE over the pixels that hit a surface "
            "is below this, in AO units (AO runs 0 to 1: 0.02 is 2% of white); the error "
            "you get is 0.7-1.0x of it in 95% of renders. Samples go where they lower it "
            "most (0: off, Samples per pixel)"
        ),
        default=TARGET_ERROR["low"],  # unset
        min=TARGET_ERROR["low"],
        max=_top(TARGET_ERROR),
        precision=4,
    )
    max_pixel_error: FloatProperty(  # type: ignore[valid-type]
        name="Max pixel error",
        description=(
            "Stop sampling a pixel once its 95% confidence half-width is below this, in AO "
            "units (0 to 1): every pixel bounded, at many more samples than Target Error "
            "(0: off)"
        ),
        default=MAX_PIXEL_ERROR["low"],  # unset
        min=MAX_PIXEL_ERROR["low"],
        max=_top(MAX_PIXEL_ERROR),
        precision=4,
    )
    viewport_spp: IntProperty(  # type: ignore[valid-type]
        name="Viewport samples",
        description=("AO rays per pixel the Rendered viewport refines to (as Cycles' "
                     "Viewport samples: apart from the final render's). The first image "
                     "comes after 1"),
        default=32,
        min=1,
        max=SPP["soft_high"],
    )
    viewport_target_error: FloatProperty(  # type: ignore[valid-type]
        name="Viewport target error",
        description=(
            "The Rendered viewport refines to this estimated RMSE (AO units) with the "
            "final render's adaptive sampling, through 4x and 2x it first, instead of to "
            "Viewport Samples (0: off)"
        ),
        default=TARGET_ERROR["low"],  # unset
        min=TARGET_ERROR["low"],
        max=_top(TARGET_ERROR),
        precision=4,
    )
    use_denoising: BoolProperty(  # type: ignore[valid-type]
        name="Denoise",
        description=(
            "Denoise the rendered image with Intel Open Image Denoise, with the surface "
            "normals as a guide (as Cycles' Denoise). Needs the service installed with "
            'pip install "scenesort[denoise]". The estimated RMSE shown stays the one '
            "before denoising"
        ),
        default=False,
    )
    ao_distance: FloatProperty(  # type: ignore[valid-type]
        name="AO distance",
        description=(
            "Occluders farther than this from the shaded point are ignored "
            "(0: the World's Ambient Occlusion distance, as Cycles' AO pass uses; "
            "10 m without a World)"
        ),
        default=DISTANCE["low"],  # unset: the World's
        min=DISTANCE["low"],
        soft_max=100.0,
        subtype="DISTANCE",
    )
    seed: IntProperty(  # type: ignore[valid-type]
        name="Seed", description="Random seed of the AO samples", default=SEED["default"],
        min=SEED["low"], max=SEED["high"],
    )
    engine: EnumProperty(  # type: ignore[valid-type]
        name="Engine",
        items=ENGINE_ITEMS,
        default=ENGINE["default"],
    )
    # The last build, filled by scenesort.build_bvh and scenesort.render_ao.
    has_build: BoolProperty(default=False)  # type: ignore[valid-type]
    build_total_ms: FloatProperty(name="Total ms")  # type: ignore[valid-type]
    build_compile_ms: FloatProperty(name="Compile ms")  # type: ignore[valid-type]
    build_cached: BoolProperty(name="Cached")  # type: ignore[valid-type]
    build_method: StringProperty(name="Method")  # type: ignore[valid-type]
    build_leaf_size: IntProperty(name="Leaf size")  # type: ignore[valid-type]
    build_triangles: IntProperty(name="Triangles")  # type: ignore[valid-type]
    build_nodes: IntProperty(name="Nodes")  # type: ignore[valid-type]
    build_sah_cost: FloatProperty(name="SAH cost")  # type: ignore[valid-type]
    build_mtris_per_s: FloatProperty(name="MTris/s")  # type: ignore[valid-type]
    build_phases: CollectionProperty(type=SCENESORT_PG_phase)  # type: ignore[valid-type]
    build_history: CollectionProperty(type=SCENESORT_PG_build)  # type: ignore[valid-type]


class SCENESORT_PG_status(bpy.types.PropertyGroup):
    """`window_manager.scenesort`: runtime state; not saved, so errors never touch the scene."""

    connected: BoolProperty(default=False)  # type: ignore[valid-type]
    url: StringProperty()  # type: ignore[valid-type]
    version: StringProperty()  # type: ignore[valid-type]
    mismatch: BoolProperty(default=False)  # type: ignore[valid-type] - other version answered
    device: StringProperty()  # type: ignore[valid-type]
    message: StringProperty()  # type: ignore[valid-type]
    error: StringProperty()  # type: ignore[valid-type]
    busy: BoolProperty(default=False)  # type: ignore[valid-type]
    progress: StringProperty()  # type: ignore[valid-type]
    last_render_ms: FloatProperty()  # type: ignore[valid-type]
    # what the last render achieved (the job's status); last_rmse < 0: not known
    last_rmse: FloatProperty(  # type: ignore[valid-type]
        name="Est. RMSE",
        description=(
            "The render's estimate of its RMSE over the pixels that hit a surface, against "
            "the AO of infinitely many samples, in AO units (AO runs 0 to 1)"
        ),
        default=-1.0,
    )
    last_spp_mean: FloatProperty(name="Mean spp")  # type: ignore[valid-type]
    last_spp_max: IntProperty(name="Max spp")  # type: ignore[valid-type]
    last_rays: IntProperty(name="Rays")  # type: ignore[valid-type]
    last_device: StringProperty(name="Device")  # type: ignore[valid-type]  # F12's, "" before
    last_upload_bytes: IntProperty()  # type: ignore[valid-type]
    renders: IntProperty()  # type: ignore[valid-type]


CLASSES = (SCENESORT_PG_phase, SCENESORT_PG_build, SCENESORT_PG_settings, SCENESORT_PG_status)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.scenesort = PointerProperty(type=SCENESORT_PG_settings)
    bpy.types.WindowManager.scenesort = PointerProperty(type=SCENESORT_PG_status)


def unregister() -> None:
    del bpy.types.WindowManager.scenesort
    del bpy.types.Scene.scenesort
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
