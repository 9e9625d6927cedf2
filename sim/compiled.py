"""Compiled kernels: numba's ``njit`` with its on-disk cache.

The control stack's arrays are tiny (N <= 35 robots, a few obstacles), so
numpy's per-call overhead, not arithmetic, dominates a control tick; the hot
inner functions are written as loops and compiled. ``cache=True`` stores the
machine code beside the source (``__pycache__``) so a second run pays no
compile time; numba itself falls back to a user-wide cache folder when the
install is read-only (or to ``NUMBA_CACHE_DIR`` when set). Where no folder
is writable at all the kernels are compiled anew in each process.

Floating-point semantics follow numpy's (``error_model="numpy"``: x / 0 is
inf or NaN, not an exception). Kernels are plain functions over float64 arrays: no MuJoCo, no I/O. Each has
one implementation; the public function that calls it checks shapes and
documents units.
"""

from __future__ import annotations

from typing import Callable

import numba


def kernel(function: Callable) -> Callable:
    """Compile ``function`` in nopython mode with the on-disk cache (without it
    when no cache folder is writable)."""
    try:
        return numba.njit(cache=True, error_model="numpy")(function)
    except RuntimeError:  # "cannot cache function ...: no locator available"
        return numba.njit(error_model="numpy")(function)
