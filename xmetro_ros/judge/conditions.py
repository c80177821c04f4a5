"""The conditions U is calibrated in: incidence-angle bins × exposure levels (Mondrian conformal categories).

One multiplier per axis for a whole scan under-covers where the error's spread grows faster than the model's σ̂
says: beyond the grazing angle (80-90°: 85-88 % on held-out scans) and at mid incidence at the shortest exposure.
The calibration (:func:`xmetro_ros.learn.uncertainty.calibrate`) therefore computes the conformal multiplier per
*condition* — the incidence angle acos(Inc) in 10° bins crossed with the exposure levels of the calibration
clouds — and the card's ``uncertainty.conditional`` block holds them; a point's U uses its condition's multiplier.
A condition the calibration saw too few points of has no multiplier: those points get no U (NaN, flag
NO_UNCERTAINTY) rather than a guess. Cards without the block keep one multiplier per axis.

A card calibrated on surfaces of every class (flat, convex, concave, saddle, sharp: :mod:`.surface_class`) also
holds the multipliers per surface class (``conditional.by_surface``): the table of :func:`multiplier_table` then stacks
(1 + classes) blocks of the conditions' rows, block 0 over all classes (points without a class: unorganized scans,
scan borders) and block 1 + k for class k; a class's condition with too few calibration points takes block 0's
multiplier.

Units: degrees (incidence, from the ``Inc`` feature = cos of the angle between the normal and the laser direction),
milliseconds (exposure, the ``exposure_time`` feature).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = ["INCIDENCE_EDGES_DEG", "MIN_POINTS", "condition_index", "exposure_edges", "interior_edges",
           "multiplier_table", "row_multipliers"]

INCIDENCE_EDGES_DEG = tuple(float(a) for a in range(0, 91, 10))
#: fewest calibration points of a condition (per axis) for its own multiplier: the fewest for which the finite-sample
#: conformal quantile at 95 % exists (⌈(n + 1)·0.95⌉ ≤ n). Few points make a noisy multiplier; the calibration's
#: envelope over neighbouring incidence bins (learn/uncertainty.py) keeps such a cell at least as wide as theirs.
MIN_POINTS = 19
FEATURES = ("Inc", "exposure_time")


def exposure_edges(levels: Sequence[float]) -> list[float]:
    """Bin edges (ms) between the distinct exposure levels of the calibration (geometric midpoints), open at both
    ends: an exposure between two levels joins the nearer one (in ratio)."""
    lv = np.unique(np.asarray(levels, np.float64))
    lv = lv[np.isfinite(lv) & (lv > 0)]
    mids = np.sqrt(lv[1:] * lv[:-1]) if len(lv) > 1 else np.zeros(0)
    return [0.0, *mids.tolist(), float("inf")]


def interior_edges(incidence_edges: Sequence[float], exp_edges: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """(cos of the interior incidence edges, interior exposure edges): a row's incidence bin is the number of
    interior edges its angle reaches (cos Inc ≤ cos edge), its exposure bin the number of interior exposure edges
    it reaches (exposure ≥ edge) — the one rule of :func:`condition_index` and the compiled U kernel."""
    ie = np.asarray(incidence_edges, np.float64)
    ee = np.asarray(exp_edges, np.float64)
    return np.cos(np.radians(ie[1:-1])), ee[1:-1].copy()


def condition_index(X: np.ndarray, feature_names: Sequence[str], incidence_edges: Sequence[float],
                    exp_edges: Sequence[float]) -> np.ndarray:
    """(M,) int64 condition of each feature row: incidence bin × len(exposure bins) + exposure bin; −1 where the
    row's Inc or exposure is not finite. Raises ValueError when the features lack Inc or exposure_time."""
    names = list(feature_names)
    X = np.asarray(X)
    cos_i = np.asarray(X[:, names.index("Inc")], np.float64)
    exp = np.asarray(X[:, names.index("exposure_time")], np.float64)
    cos_e, exp_e = interior_edges(incidence_edges, exp_edges)
    bi = (cos_i[:, None] <= cos_e[None, :]).sum(axis=1)
    be = (exp[:, None] >= exp_e[None, :]).sum(axis=1)
    idx = bi * (len(exp_e) + 1) + be
    return np.where(np.isfinite(cos_i) & np.isfinite(exp), idx, -1).astype(np.int64)


def _cells(rows: list) -> np.ndarray:
    return np.array([[np.nan if m is None else float(m) for m in cell] for cell in rows], np.float64)


def multiplier_table(block: dict[str, Any]) -> np.ndarray:
    """(blocks × cells, 3) float64 of the block's conditional multipliers, NaN where a condition has none: one block
    of cells without ``by_surface``, else 1 + classes blocks (module doc; a class's missing cell takes block 0's)."""
    cond = block["conditional"]
    base = _cells(cond["multiplier"])
    by = cond.get("by_surface")
    if not by:
        return base
    per = [_cells(rows) for rows in by["multiplier"]]
    return np.concatenate([base, *(np.where(np.isnan(t), base, t) for t in per)])


def row_multipliers(block: dict[str, Any], X: np.ndarray, feature_names: Sequence[str],
                    surface_class: np.ndarray | None = None) -> np.ndarray:
    """(M, 3) float64 multiplier of each row: its condition's (``block["conditional"]``) — of its surface class
    (``surface_class`` (M,) int, −1 none) when the block has them — NaN for a condition the calibration had too few
    points of or a row without a condition; the per-axis multipliers for every row when the block has no
    conditional part."""
    glob = np.asarray(block["multiplier"], np.float64)
    cond = block.get("conditional")
    if not cond:
        return np.broadcast_to(glob, (len(X), len(glob)))
    table = multiplier_table(block)
    idx = condition_index(X, feature_names, cond["incidence_edges_deg"], cond["exposure_edges_ms"])
    if surface_class is not None and cond.get("by_surface"):
        n_cells = len(cond["multiplier"])
        idx = np.where(idx >= 0, idx + (np.asarray(surface_class, np.int64) + 1) * n_cells, -1)
    out = np.full((len(X), table.shape[1]), np.nan)
    ok = idx >= 0
    out[ok] = table[idx[ok]]
    return out
