"""Divide-and-conquer ray tracing, no acceleration structure kept: the task-pool variant of
the 2012 paper (sec. 5: seven children per split, dependency table, RDH) and the
breadth-first variant of the 2013 paper, over shared ray and triangle records."""

from .api import VARIANTS, dacrt_trace, dacrt_trace_mesh
from .options import DacrtOptions
from .stats import DacrtStats

__all__ = ["VARIANTS", "DacrtOptions", "DacrtStats", "dacrt_trace", "dacrt_trace_mesh"]
