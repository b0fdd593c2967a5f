"""Start-up of a local worker process (imports nothing numerical, on purpose)."""

from __future__ import annotations

import os


def init_worker(workers: int) -> None:
    """Share the machine's cores among ``workers`` processes.

    Runs before the worker imports numba or MKL, which read these variables once.
    """
    threads = str(max(1, (os.cpu_count() or 1) // max(1, workers)))
    for name in ("NUMBA_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS"):
        os.environ[name] = threads
