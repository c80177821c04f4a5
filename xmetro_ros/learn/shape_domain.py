"""The shapes a model set was calibrated on, as a range of the surface's mean curvature (card ``domain_shape``).

The per-point features carry no shape: a model trained on spheres and cylinders extrapolates silently to a concave
pocket or a sharp edge, and its intervals fail there first (docs/parts-generalisation.md). The judge therefore also
compares each point's mean curvature (:mod:`xmetro_ros.preprocess.curvature`) with the range the calibration clouds
covered — those clouds are the training campaign simulated again (same artifacts, settings and poses, new noise), so
their shapes are the training shapes. Points outside ``[lo − m, hi + m]`` (m = ``domain_margin`` × (hi − lo)) are
flagged OUT_OF_DOMAIN; U is not widened there (nothing says by how much), the flag says the interval is not vouched
for.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np

__all__ = ["PRINCIPAL_BIN_PER_MM", "PRINCIPAL_LIMIT_PER_MM", "SHAPE_QUANTILE", "fit_principal_domain",
           "fit_shape_domain", "shape_domain_of_scans"]

SHAPE_QUANTILE = 0.001  # as the multivariate domain: 0.1 % of the calibration points fall outside on each side
PRINCIPAL_BIN_PER_MM = 0.01  # cell of the (κmin, κmax) plane: the curvature noise of a plane at 0.1 ms (~±0.015)
PRINCIPAL_LIMIT_PER_MM = 0.6  # the plane's extent ±: 1/0.6 = 1.7 mm radius, below which 1 mm apart reads nothing


def fit_shape_domain(curvatures: Iterable[np.ndarray], quantile: float = SHAPE_QUANTILE) -> dict[str, Any]:
    """The card's ``domain_shape`` block from the mean curvatures (1/mm) of the calibration clouds' points (NaN
    ignored): ``{"measure", "radius_mm", "lo", "hi", "quantile", "n"}``. Raises ValueError without finite values."""
    from ..preprocess.curvature import RADIUS_MM

    c = np.concatenate([np.asarray(x, np.float64).reshape(-1) for x in curvatures] or [np.zeros(0)])
    c = c[np.isfinite(c)]
    if len(c) == 0:
        raise ValueError("no finite curvature: the shape domain needs organized calibration scans")
    return {"measure": "mean curvature 1/mm from normals 1 mm apart on the scan grid "
                       "(xmetro_ros.preprocess.curvature)",
            "radius_mm": RADIUS_MM, "lo": float(np.quantile(c, quantile)), "hi": float(np.quantile(c, 1 - quantile)),
            "quantile": float(quantile), "n": len(c),
            "rule": "a point whose curvature lies outside [lo - m, hi + m], m = domain_margin * (hi - lo), is "
                    "OUT_OF_DOMAIN (U not widened); unorganized scans are not checked"}


def fit_principal_domain(kappas: Iterable[np.ndarray], quantile: float = SHAPE_QUANTILE,
                         bin_per_mm: float = PRINCIPAL_BIN_PER_MM, limit: float = PRINCIPAL_LIMIT_PER_MM
                         ) -> dict[str, Any]:
    """The ``principal`` part of the card's ``domain_shape`` block from the principal curvatures (κmin, κmax) (N, 2)
    in 1/mm of the calibration clouds' points: the cells of the (κmin, κmax) plane (``bin_per_mm`` wide, over
    ±``limit``) that the calibration points occupy, less the sparsest cells holding ``quantile`` of the points
    together (isolated noise), then one cell around every kept cell (the margin). A point is in the shape domain
    when its cell is one of them (judge/surface_class.py). Raises ValueError without finite values."""
    from scipy.ndimage import binary_dilation

    n_bins = round(2 * limit / bin_per_mm)
    counts = np.zeros((n_bins, n_bins), np.int64)
    n = 0
    for k in kappas:
        k = np.asarray(k, np.float64).reshape(-1, 2)
        k = k[np.isfinite(k).all(axis=1)]
        n += len(k)
        ij = np.floor((k + limit) / bin_per_mm).astype(np.int64)
        ij = ij[((ij >= 0) & (ij < n_bins)).all(axis=1)]
        np.add.at(counts, (ij[:, 0], ij[:, 1]), 1)
    if n == 0:
        raise ValueError("no finite principal curvature: the shape domain needs organized calibration scans")
    flat = counts.reshape(-1)
    order = np.argsort(flat, kind="stable")
    drop = order[np.cumsum(flat[order]) <= quantile * n]  # the sparsest cells, together ≤ quantile of the points
    keep = flat > 0
    keep[drop] = False
    grown = binary_dilation(keep.reshape(n_bins, n_bins), structure=np.ones((3, 3), bool))  # one cell around each
    cells = np.argwhere(grown)
    return {"measure": "principal curvatures (kmin, kmax) 1/mm from normals 1 mm apart on the scan grid "
                       "(xmetro_ros.preprocess.curvature.grid_principal_curvatures)",
            "lo_per_mm": -float(limit), "bin_per_mm": float(bin_per_mm), "n_bins": n_bins,
            "cells": cells.tolist(), "n": int(n), "quantile": float(quantile),
            "rule": "a point whose (kmin, kmax) cell, floor((k - lo) / bin), is not among cells is OUT_OF_DOMAIN "
                    "(domain_shape; U not widened); the cells are those the calibration points occupy less the "
                    "sparsest holding quantile of them, grown by one cell; domain_margin does not apply"}


def shape_domain_of_scans(scans: Iterable[Any], scanner: Any = None, quantile: float = SHAPE_QUANTILE
                          ) -> dict[str, Any]:
    """:func:`fit_shape_domain` of simulated or measured organized scans, each pre-processed as the judge does."""
    from ..preprocess import prepare_scan
    from ..preprocess.curvature import mean_curvature

    return fit_shape_domain((mean_curvature(prepare_scan(s, scanner=scanner)) for s in scans), quantile)
