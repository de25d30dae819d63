"""What the engine renders: Blender's camera model, Monte Carlo sampling, ambient
occlusion with fixed or adaptive sample counts (of a mesh or a two-level scene), and the
culling of what a camera's image cannot depend on."""

from .ao import DEFAULT_MAX_SPP, AoResult, ambient_occlusion, default_distance, render_ao
from .camera import Camera
from .cull import mesh_box, view_planes, visible_instances, visible_triangles

__all__ = [
    "DEFAULT_MAX_SPP", "AoResult", "Camera", "ambient_occlusion", "default_distance", "render_ao",
    "mesh_box", "view_planes", "visible_instances", "visible_triangles",
]
