"""How many threads the compiled kernels run on, and kernels that cost nothing to run on one.

A numba kernel compiled with ``parallel=True`` starts an OpenMP region at every call, even
when numba is set to one thread: about 0.6 us a call here (measured: a sum over 8 numbers,
0.73 us parallel on one thread against 0.17 us compiled serially). A step on the small
phantom levels makes more than a hundred such calls (25 CG iterations of four each), so
:func:`parallel_kernel` compiles every such kernel twice, in parallel and serially, and a
call runs the serial one while :func:`one_thread_below` holds the kernels to one thread.
Both compile the same source with the same options, and a parallel reduction on one thread
sums in the serial loop's order: the results are the same bits (checked by
``tests/test_solvers.py``).
"""

from __future__ import annotations

import contextlib
import functools
import threading
import types
from collections.abc import Callable, Iterator
from typing import Any

import numba


class _ThreadState(threading.local):
    """Whether the enclosing :func:`one_thread_below` holds this Python thread's kernels to
    one thread. Per thread, as numba's ``set_num_threads`` is: a simulation in another thread
    keeps its own setting."""

    one_thread = False


_STATE = _ThreadState()


@contextlib.contextmanager
def one_thread_below(unknowns: int, threshold: int) -> Iterator[None]:
    """Run the enclosed compiled kernels on one thread when ``unknowns`` < ``threshold``
    (or numba has one thread anyway), the :func:`parallel_kernel` ones compiled serially.

    Parallel reductions sum in per-thread parts, so their last bits depend on the thread
    count: below the threshold results no longer depend on the machine's core count.
    """
    previous_threads = numba.get_num_threads()
    previous_serial = _STATE.one_thread
    serial = unknowns < threshold or previous_threads == 1
    if not serial:
        yield
        return
    if previous_threads != 1:
        numba.set_num_threads(1)
    _STATE.one_thread = True
    try:
        yield
    finally:
        _STATE.one_thread = previous_serial
        if previous_threads != 1:
            numba.set_num_threads(previous_threads)


def running_on_one_thread() -> bool:
    """Whether the calling code is inside a :func:`one_thread_below` that holds one thread."""
    return _STATE.one_thread


def parallel_kernel(
    function: Callable[..., Any] | None = None, *, prange: bool = True, **options: Any
) -> Any:
    """Compile ``function`` (numba ``njit``, ``cache=True``, ``options``) twice: the
    returned function's ``parallel`` build (``parallel=True``) and its ``serial`` build (prange
    loops as plain loops). Calling it runs the serial build inside a one-thread
    :func:`one_thread_below`, else the parallel one. Use as ``@parallel_kernel`` or
    ``@parallel_kernel(fastmath=False)``.

    ``prange=False`` is for a serial kernel that calls parallel kernels (CG's loop): both of
    its builds are serial, each calling the matching build of those kernels. Such a kernel
    is compiled with a copy of its module's globals taken where it is defined, so define it
    after everything it uses (otherwise numba names the missing global when it compiles).

    The serial build is compiled from the same code under another qualified name
    (``<name>__serial``), so numba caches it in a file of its own: numba's cache index does
    not key on ``parallel``, and the two builds would otherwise load each other.
    """
    if function is None:
        return lambda f: parallel_kernel(f, prange=prange, **options)
    parallel_build = numba.njit(cache=True, parallel=prange, **options)(
        _with_kernels(function, "parallel", suffix="")
    )
    serial_build = numba.njit(cache=True, **options)(
        _with_kernels(function, "serial", suffix="__serial")
    )
    state = _STATE

    # A plain function, not an object with __call__: the dispatch adds one Python call.
    @functools.wraps(function)
    def kernel(*args: Any) -> Any:
        return (serial_build if state.one_thread else parallel_build)(*args)

    kernel.parallel = parallel_build  # type: ignore[attr-defined]
    kernel.serial = serial_build  # type: ignore[attr-defined]
    return kernel


def _with_kernels(function: Callable[..., Any], build: str, suffix: str) -> Callable[..., Any]:
    """``function`` itself, or a copy renamed with ``suffix`` and, if it calls
    :func:`parallel_kernel` s, with globals that name their ``build`` ("parallel" or
    "serial"): numba compiles calls to its own dispatchers, not to Python functions."""
    names = function.__code__.co_names
    kernels = {
        name: getattr(value, build)
        for name in names
        if _is_parallel_kernel(value := function.__globals__.get(name))
    }
    if not kernels and not suffix:
        return function
    code = function.__code__
    if suffix:
        code = code.replace(co_name=code.co_name + suffix)
    # Without kernels to swap, the module's own globals, live: the kernel may use functions
    # defined after it.
    namespace = {**function.__globals__, **kernels} if kernels else function.__globals__
    copy = types.FunctionType(
        code,
        namespace,
        function.__name__ + suffix,
        function.__defaults__,
        function.__closure__,
    )
    copy.__qualname__ = function.__qualname__ + suffix
    copy.__module__ = function.__module__
    copy.__doc__ = function.__doc__
    return copy


def _is_parallel_kernel(value: object) -> bool:
    return callable(value) and hasattr(value, "parallel") and hasattr(value, "serial")
