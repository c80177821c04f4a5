"""Calibration of the judge's d and U along the measured normal (:class:`xmetro_ros.judge.along_normal.AlongNormal`).

Split-conformal, on calibration rows the model never trained on:

- m per exposure level × surface class: the ``level`` quantile (finite-sample rank ⌈(n + 1)·level⌉, crepes through
  :func:`.conformal.conformal_multiplier`) of |(actual − d)·n| / σ over the rows with a measured noise σ;
- c per incidence bin × surface class × axis × whether the axis carries the deviation
  (:func:`xmetro_ros.judge.along_normal.axis_group`): the same quantile of the c_a each row needs for
  |actual − d'|_a ≤ U'_a (:mod:`xmetro_ros.judge.along_normal`'s U'_a, θ_a = c_a·τ_a, τ_a the row's measured tilt
  noise, or c_a·σ·g_a for the grid models; 0 where U_n·|n_a| already covers it;
  :func:`xmetro_ros.judge.along_normal.allowance_scale`); a bin with fewer than ``min_rows`` such rows takes the c
  of the class's rows of that axis and group over all bins (of all the class's rows of the axis when those are
  few).
  One c per class pooled over the axes and incidences (0.9.0's block) left X short near normal incidence and Y
  over (docs/along-normal.md).

A group with fewer than ``min_rows`` rows gets no factor (NaN: the judge keeps the model's d and U there).
"""

from __future__ import annotations

import numpy as np

from ..judge.along_normal import (
    MEASURED_TILT,
    AlongNormal,
    allowance_scale,
    axis_group,
    exposure_level,
    grid_spacings_mm,
    incidence_bin,
)
from ..judge.conditions import INCIDENCE_EDGES_DEG
from ..judge.measured_noise import NORMAL_FEATURES
from .conformal import conformal_multiplier

__all__ = ["MIN_ROWS", "fit", "fit_rows"]

MIN_ROWS = 200


def fit(d: np.ndarray, actual: np.ndarray, normals: np.ndarray, noise: np.ndarray, surface_class: np.ndarray,
        exposure_ms: np.ndarray, spacings_mm: np.ndarray, exposure_edges: np.ndarray, n_classes: int,
        level: float = 0.95, min_rows: int = MIN_ROWS, allowance_model: str = "tangent_slopes",
        incidence: np.ndarray | None = None, tilt: np.ndarray | None = None) -> AlongNormal:
    """The block from calibration rows: model errors ``d`` and true errors ``actual`` (M, 3) mm (same sign), the
    judge's unit ``normals`` (M, 3), measured ``noise`` (M,) mm (NaN: none; such rows are left out), surface classes
    (M,) (−1: none, left out), each row's exposure (ms) and grid spacings (M, 2) (h_x, h_y) mm
    (:func:`~xmetro_ros.judge.along_normal.grid_spacings_mm`); ``exposure_edges`` the interior edges between the
    exposure levels, ``n_classes`` the card's surface classes, ``incidence`` (M,) each row's Inc feature (cos of
    the angle between normal and laser; None: one incidence bin, 0-90°), ``tilt`` (M, 3) each row's measured tilt
    noise (radians, :mod:`xmetro_ros.preprocess.tilt_noise`; NaN: none, such rows get no c; needed by the
    ``measured_tilt`` allowance model, ignored by the grid models)."""
    if allowance_model == MEASURED_TILT and tilt is None:
        raise ValueError("along_normal: the measured_tilt allowance is fitted on the rows' measured tilt noise")
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
    # the c_a each row needs for |actual − d'|_a ≤ U_n·√(n_a² + (c_a·σ·g_a)²), U_n = m·σ, d' = (d·n)·n
    m_row = mult[lvl.clip(0, len(edges)), np.where(ok, cls, 0)]
    un = m_row * sigma
    dp = np.einsum("ij,ij->i", d, n)[:, None] * n
    scale = allowance_scale(np.where(ok[:, None], n, 0.0), sigma,
                            np.asarray(spacings_mm, np.float64).reshape(-1, 2), allowance_model, tilt)
    with np.errstate(invalid="ignore", divide="ignore"):
        s2 = ((actual - dp) / un[:, None]) ** 2 - n**2
        need = np.sqrt(np.maximum(s2, 0.0)) / np.maximum(scale, 1e-12)
    edges_deg = np.asarray(INCIDENCE_EDGES_DEG if incidence is not None else (0.0, 90.0), np.float64)
    inc = np.zeros(len(sigma)) if incidence is None else np.asarray(incidence, np.float64).reshape(-1)
    ok_c = ok & np.isfinite(un) & np.isfinite(inc) & np.isfinite(scale).all(axis=1)
    b_row = incidence_bin(edges_deg, inc)
    allowance = np.full((len(edges_deg) - 1, n_classes, 3, 2), np.nan)
    group = axis_group(n)  # 0: the axis carries the deviation, 1: it does not

    def q(rows: np.ndarray, a: int) -> float:
        return conformal_multiplier(need[rows, a], np.ones(int(rows.sum())), level)

    for k in range(n_classes):
        g = ok_c & (cls == k)
        if g.sum() < min_rows:
            continue
        for a in range(3):
            for j in (0, 1):
                ga = g & (group[:, a] == j)
                pooled = q(ga, a) if ga.sum() >= min_rows else q(g, a)
                for b in range(len(edges_deg) - 1):
                    gb = ga & (b_row == b)
                    allowance[b, k, a, j] = q(gb, a) if gb.sum() >= min_rows else pooled
    return AlongNormal(edges, mult, allowance, float(level), allowance_model, edges_deg)


def fit_rows(X: np.ndarray, names: list[str], y: np.ndarray, pred: np.ndarray, surface_class: np.ndarray,
             noise: np.ndarray, exposure_edges: np.ndarray, n_classes: int, level: float = 0.95,
             tilt: np.ndarray | None = None, allowance_model: str = MEASURED_TILT) -> AlongNormal:
    """:func:`fit` on feature rows X (M, F) named ``names`` (the normal N_x, N_y, N_z, ``exposure_time`` and the
    two densities give n, the exposure and the grid spacings), targets ``y`` and the model's predictions ``pred``
    (M, 3) mm in the same sign, the rows' measured ``noise`` (M,) and ``tilt`` noise (M, 3)."""
    X = np.asarray(X, np.float64)
    col = {c: names.index(c) for c in (*NORMAL_FEATURES, "exposure_time", "lateral_density", "direction_density")}
    spacing = grid_spacings_mm(X[:, col["lateral_density"]], X[:, col["direction_density"]])
    return fit(pred, y, X[:, [col[c] for c in NORMAL_FEATURES]], noise, surface_class, X[:, col["exposure_time"]],
               spacing, exposure_edges, n_classes, level, allowance_model=allowance_model,
               incidence=X[:, names.index("Inc")] if "Inc" in names else None, tilt=tilt)
