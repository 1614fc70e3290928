"""Matrix products shaped to stay out of OpenBLAS's threaded path.

OpenBLAS runs a GEMM on several threads once m·n·k ≥ 262144 (its SMP threshold). On few or
shared cores, and under ``pytest -n``, those threads spin and contend: products over a long
inner dimension measured 10–50× slower than single-threaded. The products here are therefore
summed over row blocks small enough to stay below the threshold.
"""

from __future__ import annotations

import numpy as np

from solver.arrays import FloatArray

_SMP_THRESHOLD = 262_144


def _block_rows(p: int, q: int) -> int:
    return max(8, (_SMP_THRESHOLD - 1) // max(p * q, 1))


def gram_tn(a: FloatArray, b: FloatArray | None = None) -> FloatArray:
    """``aᵀ b`` (``aᵀa`` without b) for tall a (R, P), b (R, Q), summed over row blocks."""
    b = a if b is None else b
    out = np.zeros((a.shape[1], b.shape[1]))
    block = _block_rows(a.shape[1], b.shape[1])
    for start in range(0, a.shape[0], block):
        out += a[start : start + block].T @ b[start : start + block]
    return out


def batched_gram_tn(a: FloatArray) -> FloatArray:
    """``a[k]ᵀ a[k]`` for a stack a (K, R, P), summed over row blocks."""
    out = np.zeros((a.shape[0], a.shape[2], a.shape[2]))
    block = _block_rows(a.shape[2], a.shape[2])
    for start in range(0, a.shape[1], block):
        part = a[:, start : start + block]
        out += np.matmul(part.transpose(0, 2, 1), part)
    return out
