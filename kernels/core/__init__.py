"""What every part of the engine stands on: geometry (boxes, rays, the watertight triangle
test), input validation, host launch helpers, device arrays and meshes.

Nothing here imports another package of `kernels`.
"""

from .claim import Claims, claimed_items, launch_claimed
from .device_arrays import DeviceArrays
from .hits import Hits
from .launch import cpu_cores, get_device, host_threads, load_modules, sync_ms, to_device
from .mesh import DeviceMesh, count_degenerate, degenerate_mask

__all__ = [
    "Claims", "DeviceArrays", "DeviceMesh", "Hits", "claimed_items", "count_degenerate",
    "cpu_cores", "degenerate_mask", "get_device", "host_threads", "launch_claimed",
    "load_modules", "sync_ms", "to_device",
]
