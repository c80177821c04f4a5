"""Calibration of the judge's d and U along the measured normal (:class:`xmetro_ros.judge.along_normal.AlongNormal`).

Split-conformal, on calibration rows the model never trained on:

- m per exposure level × surface class: the ``level`` quantile (finite-sample rank ⌈(n + 1)·level⌉, crepes through
  :func:`.conformal.conformal_multiplier`) of |(actual − d)·n| / σ over the rows with a measured noise σ;
- c per surface class: the same quantile of the θ / (σ/h) each row and axis needs for |actual − d'|_a ≤ U'_a with
  U_n = m·σ, pooled over the axes (0 where U_n·|n_a| already covers it).

A group with fewer than ``min_rows`` rows gets no factor (NaN: the judge keeps the model's d and U there).
"""

from __future__ import annotations

import numpy as np

from ..judge.along_normal import AlongNormal, exposure_level, grid_spacing_mm
from ..judge.measured_noise import NORMAL_FEATURES
from .conformal import conformal_multiplier

__all__ = ["MIN_ROWS", "fit", "fit_rows"]

MIN_ROWS = 200


def fit(d: np.ndarray, actual: np.ndarray, normals: np.ndarray, noise: np.ndarray, surface_class: np.ndarray,
        exposure_ms: np.ndarray, spacing_mm: np.ndarray, exposure_edges: np.ndarray, n_classes: int,
        level: float = 0.95, min_rows: int = MIN_ROWS) -> AlongNormal:
    """The block from calibration rows: model errors ``d`` and true errors ``actual`` (M, 3) mm (same sign), the
    judge's unit ``normals`` (M, 3), measured ``noise`` (M,) mm (NaN: none; such rows are left out), surface classes
    (M,) (−1: none, left out), each row's exposure (ms) and coarser grid spacing (mm); ``exposure_edges`` the
    interior edges between the exposure levels, ``n_classes`` the card's surface classes."""
    d = np.asarray(d, np.float64)
    actual = np.asarray(actual, np.float64)
    n = np.asarray(normals, np.float64)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    sigma = np.asarray(noise, np.float64).reshape(-1)
    cls = np.asarray(surface_class, np.int64).reshape(-1)
    edges = np.asarray(exposure_edges, np.float64)
    lvl = exposure_level(edges, np.asarray(exposure_ms, np.float64).reshape(-1))
    ok = (np.isfinite(sigma) & (sigma > 0) & (cls >= 0) & (cls < n_classes) & np.isfinite(n).all(axis=1)
          & np.isfinite(d).all(axis=1) & np.isfinite(actual).all(axis=1))
    rn = np.abs(np.einsum("ij,ij->i", actual - d, n)) / np.where(ok, sigma, 1.0)
    mult = np.full((len(edges) + 1, n_classes), np.nan)
    for a in range(len(edges) + 1):
        for k in range(n_classes):
            g = ok & (lvl == a) & (cls == k)
            if g.sum() >= min_rows:
                mult[a, k] = conformal_multiplier(rn[g], np.ones(int(g.sum())), level)
    # the θ each row and axis needs for |actual − d'|_a ≤ U_n·√(n_a² + θ²(1 − n_a²)), U_n = m·σ, d' = (d·n)·n
    m_row = mult[lvl.clip(0, len(edges)), np.where(ok, cls, 0)]
    un = m_row * sigma
    dp = np.einsum("ij,ij->i", d, n)[:, None] * n
    with np.errstate(invalid="ignore", divide="ignore"):
        s2 = (((actual - dp) / un[:, None]) ** 2 - n**2) / np.maximum(1.0 - n**2, 1e-12)
        need = np.sqrt(np.maximum(s2, 0.0)) / (sigma / np.asarray(spacing_mm, np.float64).reshape(-1))[:, None]
    ok_c = ok & np.isfinite(un)
    allowance = np.full(n_classes, np.nan)
    for k in range(n_classes):
        g = ok_c & (cls == k)
        if g.sum() >= min_rows:
            v = need[g].reshape(-1)
            allowance[k] = conformal_multiplier(v, np.ones(len(v)), level)
    return AlongNormal(edges, mult, allowance, float(level))


def fit_rows(X: np.ndarray, names: list[str], y: np.ndarray, pred: np.ndarray, surface_class: np.ndarray,
             noise: np.ndarray, exposure_edges: np.ndarray, n_classes: int, level: float = 0.95) -> AlongNormal:
    """:func:`fit` on feature rows X (M, F) named ``names`` (the normal N_x, N_y, N_z, ``exposure_time`` and the
    two densities give n, the exposure and h = 1 / min(densities)), targets ``y`` and the model's predictions
    ``pred`` (M, 3) mm in the same sign."""
    X = np.asarray(X, np.float64)
    col = {c: names.index(c) for c in (*NORMAL_FEATURES, "exposure_time", "lateral_density", "direction_density")}
    spacing = grid_spacing_mm(X[:, col["lateral_density"]], X[:, col["direction_density"]])
    return fit(pred, y, X[:, [col[c] for c in NORMAL_FEATURES]], noise, surface_class, X[:, col["exposure_time"]],
               spacing, exposure_edges, n_classes, level)
