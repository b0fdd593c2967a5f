"""Start-up of a local worker process: its share of the cores, and its end with the study."""

from __future__ import annotations

import ctypes
import os
import signal
import sys

# prctl(2) option: the signal the calling process gets when its parent dies.
_PR_SET_PDEATHSIG = 1


def init_worker(workers: int, parent_pid: int | None = None) -> None:
    """Share the machine's cores among ``workers`` processes, and end with the study.

    The thread policy is set with :func:`tissue.configure_threads` (numba's kernels on
    ``cores // workers`` threads, MKL sequential), not with environment variables: the
    worker may have imported numba already (unpickling its task imports ``tissue``), and
    numba refuses a thread count changed in the environment after its threads started.

    Args:
        workers: how many worker processes share the machine.
        parent_pid: the study's process; the worker exits when it is gone.
    """
    from tissue import configure_threads

    configure_threads(threads=max(1, (os.cpu_count() or 1) // max(1, workers)))
    # Ctrl-C reaches the whole process group: the study's process says what was kept and
    # ends the workers; each worker printing its own KeyboardInterrupt would bury that.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _exit_with_parent(parent_pid)


def _exit_with_parent(parent_pid: int | None) -> None:
    """Have Linux send this worker SIGTERM when the study's process dies.

    A pool's workers only notice their parent is gone when they next talk to it, i.e. after
    finishing the cell in hand: a study killed with SIGTERM or SIGKILL (not Ctrl-C, which
    reaches the whole process group) left its workers computing for up to the length of a
    176k-tet cell, on the cores a restarted study then shares with them. Elsewhere (macOS,
    Windows) the old behaviour stays.
    """
    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):
        return
    if parent_pid is not None and os.getppid() != parent_pid:
        os._exit(1)  # the parent died before the request took effect
