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

import warp as wp

MODULE_OPTIONS = {"enable_backward": False, "optimization_level": 3, "fuse_fp": False}


def cpu_target_flags(target_cpu: str, flags: str | None = None) -> str:
    """Warp's CPU compiler flags (`flags`, else `wp.config.cpu_compiler_flags`) for clang's
    target CPU `target_cpu` instead of the host's: `-march=native` (Warp expands it into the
    host's CPU and features) becomes `-target-cpu <target_cpu>`; Warp's clang takes no other
    `-march`. On x86-64 'x86-64' has no AVX2 (Warp adds F16C, and with it AVX), 'x86-64-v3'
    has AVX2 and 'x86-64-v4' AVX-512: the branches of bvh/wide_simd.h. For a module's
    `cpu_compiler_flags` option, or for `wp.config.cpu_compiler_flags` before any compile."""
    words = (flags if flags is not None else wp.config.cpu_compiler_flags or "").split()
    return " ".join(["-target-cpu", target_cpu, *(w for w in words if w != "-march=native")])
