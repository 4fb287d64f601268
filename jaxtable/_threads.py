"""BLAS threads while jaxtable fits, samples or diagnoses: one by default.

jaxtable's host code solves and decomposes small matrices many times over (fit Jacobians of
a few hundred rows by tens of columns, noise-model bases, GP kernels of a few hundred rows),
and so do the LAPACK calls inside JAX's CPU programs (LU, SVD, triangular solves: jaxlib
calls scipy's OpenBLAS). On such sizes an OpenBLAS thread pool costs more in hand-offs and
busy waiting than it gains, and numpy and scipy each bring one. Measured on 2 cores: eight
diagnoses of noise-only data (150 stops) 8.0 s → 4.5 s wall and 16 → 5.6 s of CPU with both
pools at one thread; `jaxtable diagnose` on the bundled example 10.8 → 8.8 s wall, 14.4 →
8.8 s CPU. JAX's own kernels run on XLA's thread pool and are not affected.

The public functions that fit, sample, select poses or diagnose run under `one_blas_thread`:
while they run every BLAS threadpoolctl finds (OpenBLAS, MKL, BLIS) is set to
`$JAXTABLE_BLAS_THREADS` threads (default 1; `off` leaves the pools alone), and the caller's
settings come back afterwards, so a user's own numpy work keeps its threads.

Cost per call: finding the loaded BLAS libraries (`threadpoolctl` reads the process's
loaded libraries) took ~2.4 ms a call in a diagnosis's process, and a diagnosis makes ~25
such calls (its fits, held-out scores and tests are public functions too). The libraries
found are kept (`_pools`) until a module is imported (a new library comes with an import),
and a call inside another (same thread) leaves the pools as its caller set them.
"""

import functools
import os
import sys
import threading

from threadpoolctl import ThreadpoolController

ENV = "JAXTABLE_BLAS_THREADS"


def blas_threads() -> int | None:
    """The BLAS thread count jaxtable's work runs with (None: the pools are left alone).

    Raises ValueError naming the variable when `$JAXTABLE_BLAS_THREADS` is neither a
    positive integer nor `off`."""
    raw = os.environ.get(ENV, "1").strip().lower()
    if raw in ("off", "none", ""):
        return None
    try:
        n = int(raw)
    except ValueError:
        n = 0
    if n < 1:
        raise ValueError(f"${ENV} must be a positive integer or 'off', got {raw!r}")
    return n


_found = {}  # len(sys.modules) when the libraries were found -> ThreadpoolController
_inside = threading.local()  # .active: a one_blas_thread call is under way in this thread


def _pools() -> ThreadpoolController:
    """The loaded thread-pool libraries, found again after any import."""
    key = len(sys.modules)
    if key not in _found:
        _found.clear()
        _found[key] = ThreadpoolController()
    return _found[key]


def one_blas_thread(fn):
    """Run `fn` with the BLAS pools at `blas_threads()` threads, restored afterwards (by the
    outermost such call of the thread: one inside it runs under its caller's setting)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        n = blas_threads()
        if n is None or getattr(_inside, "active", False):
            return fn(*args, **kwargs)
        _inside.active = True
        try:
            with _pools().limit(limits=n, user_api="blas"):
                return fn(*args, **kwargs)
        finally:
            _inside.active = False

    return wrapper
