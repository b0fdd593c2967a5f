"""MKL Pardiso, called directly: the sparse direct solver behind ``tissue.sim.solvers``' direct
and ``reuse`` solvers.

pypardiso is the dependency that installs MKL from wheels with pip alone (and the fallback
that locates it); the calls pass zero-based CSR arrays as they are and free each instance's
factor when the instance is collected. One :class:`PardisoInstance` holds one symbolic
analysis (per pattern, matrix type and precision) and its latest numerical factor.
"""

from __future__ import annotations

import contextlib
import ctypes
import glob
import os
import sys
import weakref
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray


class PardisoError(RuntimeError):
    """MKL Pardiso returned an error code (for example -4: zero or negative pivot)."""


_PARDISO_FUNCTION: list[object] = []

# MKL's threading layers (mkl_service.h): MKL_Set_Threading_Layer takes one of these.
_MKL_THREADING_SEQUENTIAL = 1

# The prototype of MKL's ``pardiso`` (oneMKL reference: pt, maxfct, mnum, mtype, phase, n, a,
# ia, ja, perm, nrhs, iparm, msglvl, b, x, error), for 64-bit pointers and 32-bit integers.
_INT_P = ctypes.POINTER(ctypes.c_int32)
_PARDISO_ARGTYPES: list[Any] = [
    ctypes.POINTER(ctypes.c_int64), _INT_P, _INT_P, _INT_P, _INT_P, _INT_P, ctypes.c_void_p,
    _INT_P, _INT_P, _INT_P, _INT_P, _INT_P, _INT_P, ctypes.c_void_p, ctypes.c_void_p, _INT_P,
]  # fmt: skip


def pardiso_function() -> object:
    """MKL's ``pardiso`` entry point, loaded once per process.

    The ``mkl`` wheel (installed with pypardiso) puts ``libmkl_rt`` in ``<prefix>/lib``
    (``Library/bin`` on Windows): it is loaded from there, or, failing that, found by
    pypardiso's own search (which walks the whole environment: 0.7-0.9 s here, so it is only
    the fallback). Before any other MKL call, MKL is made sequential unless the thread policy
    says otherwise or the user set ``MKL_THREADING_LAYER`` (see :mod:`tissue.threads`).
    """
    if not _PARDISO_FUNCTION:
        library = _load_mkl_runtime()
        from tissue.threads import thread_policy

        if thread_policy().mkl_sequential and "MKL_THREADING_LAYER" not in os.environ:
            with contextlib.suppress(AttributeError):  # an MKL without the call: its default
                library.MKL_Set_Threading_Layer(_MKL_THREADING_SEQUENTIAL)
        function = library.pardiso
        function.argtypes = _PARDISO_ARGTYPES
        function.restype = None
        _PARDISO_FUNCTION.append(function)
    return _PARDISO_FUNCTION[0]


def _load_mkl_runtime() -> ctypes.CDLL:
    """MKL's single dynamic library (``mkl_rt``), from the environment's ``lib`` folder or
    where pypardiso finds it; raises OSError or ImportError where there is none."""
    patterns = ("lib/libmkl_rt.so*", "lib/libmkl_rt*.dylib", "Library/bin/mkl_rt*.dll")
    for pattern in patterns:
        for path in sorted(glob.glob(os.path.join(sys.prefix, pattern)), key=len):
            with contextlib.suppress(OSError):
                return ctypes.CDLL(path)
    import pypardiso

    return pypardiso.PyPardisoSolver().libmkl


def _pardiso_call(function, pt, iparm, mtype, phase, n, data, indptr, indices, b, x, nrhs):
    """One call of MKL ``pardiso``; raises PardisoError on a non-zero error code."""
    error = ctypes.c_int32(0)
    int_p = ctypes.POINTER(ctypes.c_int32)
    no_perm = np.zeros(1, dtype=np.int32)
    function(
        pt.ctypes.data_as(ctypes.POINTER(ctypes.c_int64)),
        ctypes.byref(ctypes.c_int32(1)),  # maxfct
        ctypes.byref(ctypes.c_int32(1)),  # mnum
        ctypes.byref(ctypes.c_int32(mtype)),
        ctypes.byref(ctypes.c_int32(phase)),
        ctypes.byref(ctypes.c_int32(n)),
        ctypes.c_void_p(data.ctypes.data),
        indptr.ctypes.data_as(int_p),
        indices.ctypes.data_as(int_p),
        no_perm.ctypes.data_as(int_p),
        ctypes.byref(ctypes.c_int32(nrhs)),
        iparm.ctypes.data_as(int_p),
        ctypes.byref(ctypes.c_int32(0)),  # msglvl
        ctypes.c_void_p(b.ctypes.data),
        ctypes.c_void_p(x.ctypes.data),
        ctypes.byref(error),
    )
    if error.value != 0:
        raise PardisoError(f"MKL Pardiso phase {phase} failed with error {error.value}")


def _pardiso_release(function, pt, iparm, mtype) -> None:
    """Free all of one Pardiso instance's memory (phase -1); called when it is collected."""
    empty = np.zeros(1)
    pointer = np.zeros(1, dtype=np.int32)
    with contextlib.suppress(Exception):  # nothing useful to do while collecting
        _pardiso_call(function, pt, iparm, mtype, -1, 0, empty, pointer, pointer, empty, empty, 1)


class PardisoInstance:
    """One MKL Pardiso instance for one pattern, matrix type and precision.

    Calls MKL directly (pypardiso only locates the library): zero-based CSR arrays are passed
    as they are (pypardiso copies and shifts both index arrays on every call, a few ms per
    solve on the finest meshes), and the instance's memory (the factor: hundreds of MB on
    the finest meshes) is released when the instance is collected (pypardiso never frees it).

    Args:
        mtype: 2 (SPD, Cholesky) or -2 (symmetric indefinite, Bunch-Kaufman).
        single: factorise and solve in single precision (half the memory and time; for
            preconditioners).
        indptr, indices: the upper triangle's CSR structure, int32, zero-based.
        data: the upper triangle's values in the instance's precision; refilled before each
            factorisation (Pardiso may read them again while solving).
    """

    def __init__(
        self,
        mtype: int,
        single: bool,
        indptr: NDArray[np.int32],
        indices: NDArray[np.int32],
        data: NDArray[np.floating],
    ) -> None:
        self.mtype = mtype
        self.dtype = np.float32 if single else np.float64
        self.n = indptr.shape[0] - 1
        self.indptr = indptr
        self.indices = indices
        self.data = data
        self._function = pardiso_function()
        self._pt = np.zeros(64, dtype=np.int64)
        iparm = np.zeros(64, dtype=np.int32)
        iparm[0] = 1  # the values below, not MKL's defaults
        iparm[1] = 3  # parallel nested dissection (METIS), MKL's default
        iparm[7] = 0  # iterative refinement only when pivots were perturbed
        iparm[9] = 8  # pivot perturbation 1e-8 (symmetric indefinite)
        iparm[17] = -1  # report the factor's nonzeros
        iparm[20] = 1  # Bunch-Kaufman 1x1 and 2x2 pivots (symmetric indefinite)
        iparm[27] = 1 if single else 0
        iparm[34] = 1  # zero-based indices
        self._iparm = iparm
        self._finalizer = weakref.finalize(
            self, _pardiso_release, self._function, self._pt, iparm, mtype
        )
        self._call(11, np.zeros((self.n, 1), dtype=self.dtype), 1)  # symbolic analysis

    @property
    def factor_nonzeros(self) -> int:
        """Nonzeros of the last factor (as MKL reports them)."""
        return int(self._iparm[17])

    def factorize(self) -> None:
        """Numerical factorisation of ``data``; raises PardisoError (e.g. not SPD)."""
        self._call(22, np.zeros((self.n, 1), dtype=self.dtype), 1)

    def solve(self, rhs: NDArray[np.float64], phase: int = 33) -> NDArray[np.float64]:
        """Solve with the last factor for ``rhs`` (n,) or (n, k); ``phase`` 331 / 333 is
        the forward / backward substitution alone (Pardiso's solve phases)."""
        b = np.asfortranarray(rhs, dtype=self.dtype)
        nrhs = 1 if b.ndim == 1 else b.shape[1]
        return np.ascontiguousarray(self._call(phase, b, nrhs), dtype=np.float64)

    def _call(self, phase: int, b: NDArray[Any], nrhs: int) -> NDArray[Any]:
        """Run Pardiso's ``phase`` on the right-hand sides ``b`` (Fortran order); the
        solution array (Fortran order, as ``b``)."""
        x = np.empty_like(b, order="F")
        _pardiso_call(
            self._function,
            self._pt,
            self._iparm,
            self.mtype,
            phase,
            self.n,
            self.data,
            self.indptr,
            self.indices,
            b,
            x,
            nrhs,
        )
        return x


class PardisoFactorization:
    """A factorisation held by a Pardiso instance (replaced by the instance's next one).

    Right-hand sides known ahead of time may ride along with the next solve
    (:meth:`ride_along`): a solve is bound by reading the factor, so solving them in the same
    call costs much less than a call of their own (173,229 tets, single precision: one
    right-hand side 45 ms, four together 74 ms, eight 99 ms).
    """

    def __init__(self, instance: PardisoInstance) -> None:
        self._instance = instance
        self._riders: list[tuple[NDArray[np.float64], Callable[[NDArray[np.float64]], None]]] = []

    def ride_along(
        self, block: NDArray[np.float64], receive: Callable[[NDArray[np.float64]], None]
    ) -> None:
        """Solve ``block`` (n, k) in the next :meth:`solve` call, beside its right-hand side,
        and hand the solution (n, k) to ``receive`` then."""
        self._riders.append(
            (np.asarray(block, dtype=np.float64).reshape(self._instance.n, -1), receive)
        )

    @property
    def is_cholesky(self) -> bool:
        """Whether the factor is Cholesky's, A = P^T L L^T P (the SPD matrix type): then
        :meth:`forward` and :meth:`backward` are its two halves."""
        return self._instance.mtype == 2

    def forward(self, rhs: NDArray[np.float64]) -> NDArray[np.float64]:
        """Y = L^-1 P rhs, (n,) or (n, k), for a Cholesky factor: B^T A^-1 B = Y^T Y.

        Half a solve's work (it reads the factor once instead of twice): 0.46 against
        0.93 ms for 10 right-hand sides at 4,126 tets here. Riders are not carried.
        """
        if not self.is_cholesky:
            raise ValueError("forward substitution alone needs a Cholesky (SPD) factor")
        return self._instance.solve(rhs, phase=331)

    def backward(self, halves: NDArray[np.float64]) -> NDArray[np.float64]:
        """x = P^T L^-T y: ``backward(forward(b))`` solves A x = b (Cholesky factor only)."""
        if not self.is_cholesky:
            raise ValueError("backward substitution alone needs a Cholesky (SPD) factor")
        return self._instance.solve(halves, phase=333)

    def flush(self) -> None:
        """Solve the riders now, alone (no solve came to carry them)."""
        if self._riders:
            self.solve(np.zeros((self._instance.n, 0)))

    def solve(self, rhs: NDArray[np.float64]) -> NDArray[np.float64]:
        if not self._riders:
            return self._instance.solve(rhs)
        riders, self._riders = self._riders, []
        own = np.asarray(rhs, dtype=np.float64).reshape(self._instance.n, -1)
        blocks = [own, *(block for block, _ in riders)]
        solved = self._instance.solve(np.asfortranarray(np.concatenate(blocks, axis=1)))
        start = own.shape[1]
        for block, receive in riders:
            receive(solved[:, start : start + block.shape[1]])
            start += block.shape[1]
        return np.ascontiguousarray(solved[:, : own.shape[1]]).reshape(np.shape(rhs))


def pardiso_available() -> bool:
    """MKL's Pardiso can be loaded on this platform (else the direct solver uses SuperLU)."""
    try:
        pardiso_function()
    except Exception:  # noqa: BLE001 - no MKL runtime on this platform
        return False
    return True
