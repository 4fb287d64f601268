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
"""

import functools
import os

from threadpoolctl import threadpool_limits

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


def one_blas_thread(fn):
    """Run `fn` with the BLAS pools at `blas_threads()` threads, restored afterwards."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        n = blas_threads()
        if n is None:
            return fn(*args, **kwargs)
        with threadpool_limits(limits=n, user_api="blas"):
            return fn(*args, **kwargs)

    return wrapper
