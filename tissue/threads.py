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

The process's thread policy (:func:`configure_threads`) is an explicit call, made by the
command line and the environments before they build a tissue (an environment keeps a policy
already in force: an argument left out keeps its value); importing ``tissue`` sets nothing
process-wide. Where no one calls it, the first parallel kernel applies the default policy
(:data:`DEFAULT_POLICY`). The policy:

- numba's threading layer: ``tbb`` (Intel TBB, from the ``tbb`` wheel) by default, because it
  is both fork-safe and thread-safe. numba's ``omp`` layer (GNU OpenMP) makes a child forked
  after the first parallel kernel abort ("fork() called from a process already using GNU
  OpenMP"), which breaks Gymnasium's ``AsyncVectorEnv`` with its default context; its
  ``workqueue`` layer is fork-safe but aborts when two threads run parallel kernels at once
  (a viewer's simulation thread beside an environment). ``tbb`` is used where it loads,
  then ``omp``, then ``workqueue`` (numba's own order).
- MKL (Pardiso): sequential, on the calling thread. With MKL threaded, its OpenMP workers
  and numba's spin on the same cores (a 26k-tet Newton step took 200 ms against 100 ms on
  two cores), and threaded Pardiso's factorisations are not bitwise repeatable. The choice is
  made with MKL's own ``MKL_Set_Threading_Layer`` when Pardiso is first loaded, not with an
  environment variable (which would also reach other libraries in the process); a user's
  ``MKL_THREADING_LAYER`` is respected.
- numba's thread count for meshes large enough to run their kernels in parallel
  (``tissue.sim.solvers.SERIAL_STEP_UNKNOWNS``); smaller tissues run, build and step, on one
  thread whatever this says.

Bits: a tissue below that size gives the same bits whatever the thread count (its build and
its steps run the serial builds). So does one below
``tissue.sim.solvers.SERIAL_CG_UNKNOWNS`` (40,000 unknowns; every phantom level up to 26,220
tets): its parallel kernels write each entry from one thread, in an order that does not
depend on the thread count, its CG runs on one thread, and the product with its node blocks
(``tissue.sim.solvers.node_blocks``), which runs in parallel steps too, is one part summed in
row order. Above that size CG's products split the matrix in one part per thread and its dot
products are parallel reductions, which sum in per-thread parts, so the FE methods' last
digits follow the thread count (from the phantom level of 105,004 tets up; PBD's sweep keeps
its bits): ``configure_threads(threads=1)`` makes them repeatable across machines. Measured
in docs/tissue-model.md, "Threads".
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import glob
import os
import sys
import threading
import types
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numba

from tissue.errors import ConfigError

#: numba's thread pool on this machine (NUMBA_NUM_THREADS: the cores, unless the user says).
_POOL_THREADS = int(numba.config.NUMBA_NUM_THREADS)  # type: ignore[attr-defined]

#: numba's threading layers, in the order :func:`configure_threads` tries them for ``auto``.
THREADING_LAYERS = ("tbb", "omp", "workqueue")


@dataclass(frozen=True)
class ThreadPolicy:
    """How the tissue's compiled kernels and MKL use threads (see the module docstring).

    Attributes:
        threads: numba threads for large tissues; None: numba's default (the cores).
        layer: numba's threading layer, ``tbb``, ``omp``, ``workqueue`` or ``auto`` (the
            first of :data:`THREADING_LAYERS` that loads).
        mkl_sequential: run MKL Pardiso on the calling thread (bitwise repeatable).
    """

    threads: int | None = None
    layer: str = "auto"
    mkl_sequential: bool = True

    def __post_init__(self) -> None:
        if self.threads is not None and (
            isinstance(self.threads, bool)
            or not isinstance(self.threads, int)
            or not 1 <= self.threads <= _POOL_THREADS
        ):
            raise ConfigError(
                f"threads must be a whole number from 1 to {_POOL_THREADS} "
                f"(numba's thread pool on this machine) or None; got {self.threads!r}"
            )
        if self.layer not in ("auto", *THREADING_LAYERS):
            raise ConfigError(
                f"unknown threading layer {self.layer!r}; choose one of "
                f"{', '.join(repr(name) for name in ('auto', *THREADING_LAYERS))}"
            )


#: The policy applied when no one called :func:`configure_threads` before the first parallel
#: kernel: TBB where it loads, numba's thread count, MKL sequential.
DEFAULT_POLICY = ThreadPolicy()

_POLICY: list[ThreadPolicy] = []  # the policy in force, once applied


def configure_threads(
    threads: int | None = None, layer: str | None = None, mkl_sequential: bool | None = None
) -> ThreadPolicy:
    """Set the process's thread policy for the tissue (see the module docstring).

    Call it before building a tissue (the command line and the environments do). An argument
    left out (None) keeps the value in force, or takes :data:`DEFAULT_POLICY`'s on the first
    call: ``configure_threads()`` applies the default policy where none is in force and keeps
    one that is, as an environment needs where its user set one. The threading layer and
    MKL's choice are made once per process; calling again with a different layer or MKL
    choice after they are in force raises, a different thread count is applied.

    Args:
        threads: numba threads for tissues large enough to run in parallel (None: the count
            in force; on the first call, numba's, all cores unless NUMBA_NUM_THREADS says).
        layer: ``auto`` (TBB where it loads, else numba's next), ``tbb``, ``omp`` or
            ``workqueue`` (None: the layer in force, else ``auto``).
        mkl_sequential: run MKL Pardiso sequentially (None: the choice in force, else True;
            bitwise repeatable).

    Returns:
        the policy in force.

    Raises:
        ConfigError: an invalid value, or a layer that cannot be loaded or differs from the
            one already running.
    """
    current = _POLICY[0] if _POLICY else DEFAULT_POLICY
    policy = ThreadPolicy(
        current.threads if threads is None else threads,
        current.layer if layer is None else layer,
        current.mkl_sequential if mkl_sequential is None else mkl_sequential,
    )
    if _POLICY:
        if (policy.layer, policy.mkl_sequential) != (current.layer, current.mkl_sequential):
            raise ConfigError(
                f"the thread policy is already in force (layer {current.layer!r}, MKL "
                f"sequential {current.mkl_sequential}); call configure_threads once, before "
                "building a tissue"
            )
        _POLICY[0] = policy
    else:
        _apply_layer(policy.layer)
        _POLICY.append(policy)
    if policy.threads is not None:
        numba.set_num_threads(policy.threads)
    return policy


def thread_policy() -> ThreadPolicy:
    """The policy in force (applying :data:`DEFAULT_POLICY` if none is yet)."""
    if not _POLICY:
        configure_threads()
    return _POLICY[0]


def _apply_layer(layer: str) -> None:
    """Make numba use ``layer`` (``auto``: TBB where it loads) for its first parallel launch."""
    launched = _launched_layer()
    if layer == "auto":
        if launched is None:
            _load_tbb_library()  # numba's default order then picks TBB where it loads
        return
    if launched is not None:
        if launched != layer:
            raise ConfigError(
                f"numba already runs the {launched!r} threading layer; call "
                f"configure_threads(layer={layer!r}) before any parallel kernel runs"
            )
        return
    if layer == "tbb" and not _load_tbb_library():
        raise ConfigError(
            "the 'tbb' threading layer needs Intel TBB: pip install tbb (or choose "
            "layer='omp' or 'workqueue')"
        )
    numba.config.THREADING_LAYER = layer  # type: ignore[attr-defined]


def _launched_layer() -> str | None:
    """numba's threading layer if a parallel kernel has already started it, else None."""
    try:
        return str(numba.threading_layer())
    except ValueError:  # no parallel kernel has run yet
        return None


def _load_tbb_library() -> bool:
    """Make TBB's runtime loadable for numba's TBB layer; whether it is.

    pip's ``tbb`` wheel puts ``libtbb.so.12`` in the environment's ``lib`` folder, where the
    dynamic loader does not look, so numba's TBB layer would fail to load and numba would fall
    back to GNU OpenMP. Loading the library first, globally, lets numba's layer find it.
    """
    try:
        from numba.np.ufunc import tbbpool  # type: ignore[attr-defined]  # noqa: F401
    except ImportError:
        pass
    else:
        return True
    patterns = ("lib/libtbb.so.12*", "lib/libtbb.12*.dylib", "Library/bin/tbb12*.dll")
    for pattern in patterns:
        for path in sorted(glob.glob(os.path.join(sys.prefix, pattern)), key=len):
            try:
                ctypes.CDLL(path, mode=ctypes.RTLD_GLOBAL)
                from numba.np.ufunc import tbbpool  # type: ignore[attr-defined]  # noqa: F401, F811
            except (OSError, ImportError):
                continue
            return True
    return False


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
        if state.one_thread:
            return serial_build(*args)
        if not _POLICY:
            thread_policy()  # the layer is chosen before the first parallel launch
        return parallel_build(*args)

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
