"""Small dense linear algebra shared by the compiled kernels of every stage.

The echo fits (:mod:`echoloc.tof._echoes_kernels`) and the localisation
(:mod:`echoloc.localise._locate_kernels`) both solve small systems, once per fit step or echo
combination, where numpy's LAPACK call would allocate and cost more than the work. One
solver serves both, so that a fix to it reaches both. numba's cache checks only the file
of the function it compiled: after editing this module, delete the kernel modules'
``__pycache__`` folders (a fresh install has none).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from echoloc._jit import njit


@njit(cache=True, inline="always")
def solve_in_place(
    m: NDArray[np.float64], v: NDArray[np.float64], x: NDArray[np.float64]
) -> bool:  # pragma: no cover - compiled
    """Solve the small system m x = v by Gaussian elimination with partial pivoting, overwriting
    ``m`` and ``v`` (no allocation); False, with ``x`` untouched, if a pivot is zero or not
    finite (a singular or non-finite system). Golub & Van Loan, "Matrix Computations", 4th ed.,
    algorithm 3.4.1 (Gaussian elimination with partial pivoting) and 3.1.2 (back substitution)."""
    n = m.shape[0]
    for col in range(n):
        pivot = col
        for row in range(col + 1, n):
            if abs(m[row, col]) > abs(m[pivot, col]):
                pivot = row
        if m[pivot, col] == 0.0 or not np.isfinite(m[pivot, col]):
            return False
        if pivot != col:
            for k in range(n):
                m[col, k], m[pivot, k] = m[pivot, k], m[col, k]
            v[col], v[pivot] = v[pivot], v[col]
        for row in range(col + 1, n):
            f = m[row, col] / m[col, col]
            for k in range(col, n):
                m[row, k] -= f * m[col, k]
            v[row] -= f * v[col]
    for row in range(n - 1, -1, -1):
        s = v[row]
        for k in range(row + 1, n):
            s -= m[row, k] * x[k]
        x[row] = s / m[row, row]
    return True
