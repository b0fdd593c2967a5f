"""The first run after installing: the tissue's compiled kernels, said and done up front.

numba compiles the tissue's kernels on their first call and caches them on disk; the first
run after an installation spends one to two minutes compiling (measured on two cores), the
later ones load them in a second. Commands say so before it happens, and the study compiles
them in its own process before its workers start and before its progress bar's clock does,
so that the bar's estimate of the time left is not the compiler's.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import Any

from tissue.lab import compiled_kernels


def kernels_cached() -> bool:
    """Whether numba's disk cache holds the tissue's kernels (an index file each)."""
    try:
        return all(
            os.path.exists(kernel._cache._cache_file._index_path) for kernel in compiled_kernels()
        )
    except AttributeError:  # numba's cache internals moved: do not claim anything
        return True


def compile_kernels_once(log: Callable[[str], None] = print) -> float:
    """Compile the kernels now if they are not cached (a 623-tet press with every method in
    both profiles), saying so; returns the seconds it took (0 when they were cached)."""
    if kernels_cached():
        return 0.0
    log(
        "compiling the tissue's kernels: once after installing, about 1-2 minutes; later "
        "runs load them from the cache"
    )
    started = time.perf_counter()
    import tissue

    for profile in ("paper", "robust"):
        for contact in ("lm", "penalty", "prescribed", "pbd"):
            spec = tissue.TissueSpec(
                mesh=623,
                contact=contact,
                profile=profile,
                contact_params=_uncalibrated(contact, profile),
            )
            t = tissue.make_tissue(spec)
            position, quat = t.touching_pose(t.lesions[0].rest_centre_m)
            pressing = tissue.pressing_direction(quat)
            t.reset(position, quat)
            for step in range(1, 4):
                t.step(position + 0.0005 * step * pressing, quat)
    elapsed = time.perf_counter() - started
    log(f"kernels compiled in {elapsed:.0f} s")
    return elapsed


def _uncalibrated(contact: str, profile: str) -> Any:
    """PBD's stored settings (compiling needs no per-mesh calibration); None otherwise."""
    if contact != "pbd":
        return None
    from tissue.lab import PBDConfig

    return PBDConfig.for_profile(profile)


def announce_compilation(log: Callable[[str], None] = print) -> None:
    """Say that the first simulation will compile the kernels, if it will."""
    if not kernels_cached():
        log(
            "the first simulation compiles the tissue's kernels: once after installing, "
            "about 1-2 minutes"
        )
