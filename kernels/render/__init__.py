"""What the engine renders: Blender's camera model, Monte Carlo sampling, the Film's pixel
filter, ambient occlusion with fixed or adaptive sample counts (of a mesh or a two-level
scene; every setting in one `AoOptions`), and the culling of what a camera's image cannot
depend on."""

from scenesort.ao_options import (
    AO_OPTIONS,
    DEFAULT_MAX_SPP,
    PIXEL_FILTERS,
    AoOptions,
    OptionError,
    OptionSpec,
)

from .ao import (
    AoRays,
    AoResult,
    AoStats,
    AoTimings,
    ambient_occlusion,
    default_distance,
    render_ao,
    surface_ao,
)
from .camera import Camera
from .cull import mesh_box, view_planes, visible_instances, visible_triangles
from .filtered import FilmResult, render_film

__all__ = [
    "AO_OPTIONS", "DEFAULT_MAX_SPP", "AoOptions", "AoRays", "AoResult", "AoStats", "AoTimings",
    "Camera", "FilmResult", "OptionError", "OptionSpec", "PIXEL_FILTERS", "ambient_occlusion",
    "default_distance", "mesh_box", "render_ao", "render_film", "surface_ao", "view_planes",
    "visible_instances", "visible_triangles",
]
