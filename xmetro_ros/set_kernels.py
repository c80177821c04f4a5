"""Compiled (numba) row moves around the ONNX call of :class:`xmetro_ros.inference.ModelSet`: the finite-row test,
the gather of feature rows into PointNet set order and the gather of per-slot predictions back to point order.

Why compiled: numpy needs a boolean (M, F) temporary and a reduction for the finite test, and a fancy-index gather
plus a separate float32 → float64 conversion (and a NaN-row scatter) for the way back; each kernel here is one pass
over the rows. They only copy and convert (float32 → float64 is exact), so predictions are bit-identical to a
numpy gather/scatter (test/test_inference_sets.py).
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["finite_rows", "gather_rows", "scatter_back", "warm_up"]

_JIT = {"cache": True, "nogil": True}


@njit(**_JIT)
def _nonfinite_count(X: np.ndarray) -> int:
    bad = 0
    for i in range(X.shape[0]):
        for j in range(X.shape[1]):
            v = X[i, j]
            if not np.isfinite(v):
                bad += 1
                break
    return bad


@njit(**_JIT)
def _finite_index(X: np.ndarray, n_ok: int) -> np.ndarray:
    rows = np.empty(n_ok, np.int64)
    k = 0
    for i in range(X.shape[0]):
        ok = True
        for j in range(X.shape[1]):
            if not np.isfinite(X[i, j]):
                ok = False
                break
        if ok:
            rows[k] = i
            k += 1
    return rows


def finite_rows(X: np.ndarray) -> np.ndarray | None:
    """Indices (int64, ascending) of the rows of X (M, F) with every feature finite; None when all are."""
    bad = _nonfinite_count(X)
    if bad == 0:
        return None
    return _finite_index(X, X.shape[0] - bad)


@njit(**_JIT)
def _gather(X: np.ndarray, src: np.ndarray, out: np.ndarray) -> None:
    for s in range(src.shape[0]):
        r = src[s]
        for j in range(X.shape[1]):
            out[s, j] = X[r, j]


def gather_rows(X: np.ndarray, src: np.ndarray) -> np.ndarray:
    """X[src] as a new C-contiguous float32 array (len(src), F) (the sets laid end to end)."""
    out = np.empty((len(src), X.shape[1]), np.float32)
    _gather(X, src, out)
    return out


@njit(**_JIT)
def _back(y: np.ndarray, pos: np.ndarray, out: np.ndarray) -> None:
    for i in range(pos.shape[0]):
        p = pos[i]
        for j in range(y.shape[1]):
            out[i, j] = np.float64(y[p, j])


@njit(**_JIT)
def _back_rows(y: np.ndarray, pos: np.ndarray, rows: np.ndarray, out: np.ndarray) -> None:
    for i in range(pos.shape[0]):
        p = pos[i]
        r = rows[i]
        for j in range(y.shape[1]):
            out[r, j] = np.float64(y[p, j])


def scatter_back(y: np.ndarray, pos: np.ndarray, rows: np.ndarray | None, out: np.ndarray) -> None:
    """out[rows[i]] = float64(y[pos[i]]) for every i (rows None: out[i]); y (S, C) float32 per slot, out (M, C)."""
    if rows is None:
        _back(y, pos, out)
    else:
        _back_rows(y, pos, rows, out)


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernels for the types ModelSet uses."""
    X = np.zeros((2, 2), np.float32)
    X[1, 0] = np.nan
    rows = finite_rows(X)
    idx = np.zeros(1, np.int64)
    g = gather_rows(X, idx)
    out = np.empty((2, 2))
    scatter_back(g, idx, None, out)
    scatter_back(g, idx, rows, out)
