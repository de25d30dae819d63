"""The devices the engine's tests run on: the CPU always, `cuda:0` when there is one.

tests/kernels and tests/stability import `device` and `pytest_generate_tests` into their
conftest.py: every test there is parametrised over the devices present (its id ends in
`[cpu]` or `[cuda:0]`) and runs with Warp's default device set to its own, so that
`build_bvh(...)` and `dacrt_trace(...)` without a `device` run there, and tests that
launch kernels themselves pass `device` on. A test about the host only (numpy, host
threads, packaging) is marked `host_only` and runs once, on the CPU.
`benchmarks/gpu_check.py` selects the CUDA half with `-k cuda`.
"""

from __future__ import annotations

import pytest
import warp as wp

wp.config.quiet = True


def devices() -> list[str]:
    wp.init()
    return ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])


def pytest_configure(config) -> None:
    config.addinivalue_line("markers", "host_only: runs once, on the CPU (no device code)")


def pytest_generate_tests(metafunc) -> None:
    if "device" in metafunc.fixturenames:
        only_cpu = metafunc.definition.get_closest_marker("host_only") is not None
        metafunc.parametrize("device", ["cpu"] if only_cpu else devices(), indirect=True)


@pytest.fixture(autouse=True)
def device(request) -> str:
    """The test's device, also Warp's default device while it runs."""
    name = getattr(request, "param", "cpu")
    with wp.ScopedDevice(name):
        yield name
