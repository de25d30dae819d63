"""What the engine renders: Blender's camera model, Monte Carlo sampling, ambient
occlusion with fixed or adaptive sample counts."""

from .ao import DEFAULT_MAX_SPP, AoResult, ambient_occlusion, default_distance, render_ao
from .camera import Camera

__all__ = [
    "DEFAULT_MAX_SPP", "AoResult", "Camera", "ambient_occlusion", "default_distance", "render_ao",
]
