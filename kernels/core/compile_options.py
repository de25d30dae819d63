"""How every engine module is compiled: `wp.set_module_options(MODULE_OPTIONS)` at its top.

No backward pass (nothing is differentiated), -O3, and no floating-point contraction: the
watertight test relies on `bx * ay - by * ax` being the exact negation of the same edge seen
from the neighbouring triangle, and the float64 refinement, the refit's SAH sum and the
binning on every product rounded on its own, as the CPU build computes them. NVRTC fuses a
product and a sum into one FMA by default (nvcc's --fmad=true); on an H200 that let rays
escape closed meshes through shared edges (the watertightness tests) and moved t by an ulp
against the CPU. Clang, which builds the CPU kernels, fuses nothing in Warp's
one-operation-per-statement code either way, so the CPU's results stay what they were.
"""

from __future__ import annotations

MODULE_OPTIONS = {"enable_backward": False, "optimization_level": 3, "fuse_fp": False}
