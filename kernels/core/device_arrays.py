"""Device arrays of one engine call, with the bytes they hold at the peak."""

from __future__ import annotations

import numpy as np
import warp as wp

from .launch import to_device


class DeviceArrays:
    """Device arrays of one call, with the bytes they hold (peak memory accounting)."""

    def __init__(self, device):
        self.device = device
        self.bytes = 0
        self.peak = 0

    def new(self, shape, dtype, fill=None, data=None) -> wp.array:
        if data is not None:  # on CPU a view of the caller's (contiguous) array, no copy
            a = to_device(np.ascontiguousarray(data), dtype, self.device)
        elif fill is not None:
            a = wp.full(shape, fill, dtype=dtype, device=self.device)
        else:
            a = wp.empty(shape, dtype=dtype, device=self.device)
        self.bytes += a.capacity
        self.peak = max(self.peak, self.bytes)
        return a

    def hold(self, *arrays: wp.array) -> None:
        """Count arrays made elsewhere (a mesh's) that the call holds while it runs."""
        for a in arrays:
            self.bytes += a.capacity
        self.peak = max(self.peak, self.bytes)

    def free(self, *arrays: wp.array) -> None:
        for a in arrays:
            self.bytes -= a.capacity


def struct_of_arrays(struct, count: int, device):
    """An instance of the Warp struct `struct` whose array fields each hold `count` entries
    of their own dtype, uninitialised (scratch that kernels fill); other fields as made."""
    out = struct()
    for name, var in struct.vars.items():
        if wp.types.is_array(var.type):
            setattr(out, name, wp.empty(count, dtype=var.type.dtype, device=device))
    return out
