"""Launching the persistent workers of a pool application (2012 paper, sec. 3.3).

Here a worker is one thread (the paper's warp of 32 threads shares a chunk of 32 items; one
thread walks the chunk's items instead). On CPU each worker is a launch of its own, from a
host thread of its own, so that the workers run in parallel.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import warp as wp


def launch_workers(kernel, workers: int, inputs: list, device) -> None:
    """Launch a persistent worker kernel whose last argument is the first worker's index:
    on CPU one launch of one worker per host thread, so the workers run in parallel."""
    if not wp.get_device(device).is_cpu or workers == 1:
        wp.launch(kernel, dim=workers, inputs=[*inputs, 0], device=device)
        return
    wp.load_module(kernel.module, device=device)
    with ThreadPoolExecutor(workers) as ex:
        futures = [
            ex.submit(wp.launch, kernel, dim=1, inputs=[*inputs, w], device=device)
            for w in range(workers)
        ]
        for f in futures:
            f.result()
