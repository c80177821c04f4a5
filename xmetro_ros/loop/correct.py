"""Corrections the loop adds once an effect is traced (mm, artifact frame).

- ``offset``: a parametric per-identity rigid translation (one 3-vector per profile / pass / pose). Sphere and
  cylinder errors are along the nominal normal n, and a translation w of the points changes the normal error by
  n·w, so w is the (ridge-regularised) least-squares solution of n·w = residual·n over the identity's points; the
  correction added to the predicted error is (n·w) n. It is *cross-fitted*: the points of each identity are cut
  into interleaved blocks of consecutive points, the offset is fitted on the even blocks and applied to the odd
  ones and vice versa, so every corrected point was held out from its own offset's fit.
- ``feature``: the traced variable becomes a model feature and the model family is retrained (``model.py``).
"""

from __future__ import annotations

import numpy as np

__all__ = ["apply_offsets", "block_parity", "cross_fit_offsets", "fit_offsets"]


def block_parity(order: np.ndarray, block_size: int) -> np.ndarray:
    """0/1 per point: interleaved blocks of ``block_size`` consecutive points (acquisition order)."""
    return (np.asarray(order, dtype=np.int64) // max(1, block_size)) % 2


def fit_offsets(
    residual: np.ndarray, normals: np.ndarray, keys: np.ndarray, ridge: float = 1e-3
) -> tuple[np.ndarray, np.ndarray]:
    """Per-key translation w (K, 3) mm such that n·w ≈ residual·n; returns (unique keys, w).

    Batched normal equations (Σ n nᵀ + ridge·count·I) w = Σ n (r·n), one 3×3 system per key.
    """
    n = np.asarray(normals, dtype=float)
    rn = np.einsum("ij,ij->i", np.asarray(residual, dtype=float), n)
    uk, inv = np.unique(keys, return_inverse=True)
    inv = inv.reshape(-1)
    K = len(uk)
    cnt = np.bincount(inv, minlength=K).astype(float)
    A = np.empty((K, 3, 3))
    b = np.empty((K, 3))
    for i in range(3):
        b[:, i] = np.bincount(inv, weights=n[:, i] * rn, minlength=K)
        for j in range(3):
            A[:, i, j] = np.bincount(inv, weights=n[:, i] * n[:, j], minlength=K)
    A += (ridge * np.maximum(cnt, 1.0))[:, None, None] * np.eye(3)
    w = np.linalg.solve(A, b[..., None])[..., 0]
    return uk, w


def apply_offsets(normals: np.ndarray, keys: np.ndarray, uk: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Predicted error (N, 3) mm of the offsets: (n·w_key) n; keys not fitted get 0."""
    pos = np.clip(np.searchsorted(uk, keys), 0, max(len(uk) - 1, 0))
    known = (uk[pos] == keys) if len(uk) else np.zeros(len(keys), bool)
    wk = np.where(known[:, None], w[pos], 0.0)
    return np.einsum("ij,ij->i", normals, wk)[:, None] * normals


def cross_fit_offsets(
    residual: np.ndarray, normals: np.ndarray, keys: np.ndarray, order: np.ndarray, block_size: int = 24,
    ridge: float = 1e-3, groups: np.ndarray | None = None,
) -> np.ndarray:
    """Out-of-sample per-key offset correction (N, 3) mm: fitted on one block parity, applied to the other. With
    ``groups`` (for keys shared by several groups, e.g. the repeats of a sensor position) the halves are the
    groups' parities instead: fitted on some repeats, applied to the others."""
    par = (np.asarray(groups, dtype=np.int64) % 2) if groups is not None else block_parity(order, block_size)
    out = np.zeros((len(keys), 3))
    for p in (0, 1):
        fit = par != p
        if not fit.any():
            continue
        uk, w = fit_offsets(residual[fit], normals[fit], keys[fit], ridge)
        ap = par == p
        out[ap] = apply_offsets(normals[ap], keys[ap], uk, w)
    return out
