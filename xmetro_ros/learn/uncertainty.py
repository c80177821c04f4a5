"""Calibrated 95 % intervals per point and axis: split-conformal calibration by cloud, the multivariate domain,
and the interval metrics (coverage, width, sharpness against the simulator's oracle interval, rank correlation).

Method (docs/uncertainty.md):

* σ̂: the model's spread per point and axis (the PointNet spread head, ONNX output ``log_sigma``; 1 mm for members
  without one, which makes the scores plain absolute residuals).
* Calibration clouds are held out BY CLOUD from training (whole scans the model never saw), so the interval holds
  on new clouds, not only on new points of the training clouds. Nonconformity score |y − ŷ| / σ̂ per axis,
  computed with the published predictions (ONNX Runtime, each cloud partitioned into sets as at inference).
* A floor ``SIGMA_FLOOR_MM`` is added to σ̂ (scores |y − ŷ| / (σ̂ + floor)): the spread head can learn σ̂ → 0
  where the training error is identically zero, while the prediction itself is never exact (sub-µm residuals).
* Rows whose measured error on an axis is identically zero by construction carry no information on that axis'
  spread (the axial error of a cylinder: targets project onto the nominal surface) and are left out of that
  axis' scores — otherwise a third of the scores would be ~0 and the quantile would under-cover every other point.
* crepes' ``ConformalRegressor`` (normalized: ``sigmas``) gives the score quantile at the finite-sample level
  ⌈(n + 1)·confidence⌉ / n; the multiplier is the half-width it returns for σ̂ = 1. U = multiplier × σ̂.
* Conditional (Mondrian) multipliers: the same quantile per calibration condition — incidence angle in 10° bins ×
  exposure level (judge/conditions.py) — so that U holds at 95 % in each of them, not only on average (one
  multiplier per axis covered 85-88 % beyond the grazing angle and 92 % at mid incidence at 0.1 ms).
* The multivariate domain: Mahalanobis distance in the standardized feature space (ridge-regularized covariance
  of the training rows), threshold = its ``quantile`` on the training rows; stored in the card as ``domain_mv``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..judge.conditions import FEATURES as CONDITION_FEATURES
from ..judge.conditions import INCIDENCE_EDGES_DEG, MIN_POINTS, condition_index, exposure_edges
from ..judge.inference import AXES, ModelSet, update_card
from ..judge.measured_noise import NORMAL_FEATURES, effective_sigma
from ..preprocess.noise import MIN_SAMPLES as NOISE_MIN_SAMPLES
from ..preprocess.noise import WINDOW as NOISE_WINDOW
from .conformal import conformal_multiplier

__all__ = ["DOMAIN_QUANTILE", "SIGMA_FLOOR_MM", "calibrate", "conditional_multipliers", "conformal_multiplier",
           "cross_conformal_by_cloud", "fit_domain", "interval_metrics", "predict_clouds"]

ENVELOPE_BINS = 1  # conditional multipliers: the max over the incidence bins either side (see conditional_multipliers)
SIGMA_FLOOR_MM = 0.001  # 1 µm: below any real spread of the scanner (> 2 µm), above the sub-µm prediction noise
DOMAIN_QUANTILE = 0.999  # training points beyond it count as outside: 0.1 % of the training data by construction
_RIDGE = 1e-3  # added to the standardized covariance: features that are (nearly) collinear stay invertible


def fit_domain(X_train: np.ndarray, quantile: float = DOMAIN_QUANTILE) -> dict[str, Any]:
    """The multivariate domain of the training rows X (M, F): ``{"method", "mean", "whiten", "threshold",
    "quantile"}`` with whiten (F, F) such that ‖(x − mean) @ whiten‖ is the Mahalanobis distance."""
    X = np.asarray(X_train, np.float64)
    X = X[np.all(np.isfinite(X), axis=1)]
    if len(X) < X.shape[1] + 2:
        raise ValueError(f"the domain needs more than {X.shape[1] + 1} finite training rows, got {len(X)}")
    mean = X.mean(0)
    std = X.std(0)
    std = np.where(std > 1e-12, std, 1.0)
    Z = (X - mean) / std
    cov = np.cov(Z, rowvar=False) + _RIDGE * np.eye(X.shape[1])
    L = np.linalg.cholesky(cov)
    whiten = np.diag(1.0 / std) @ np.linalg.inv(L).T
    z = (X - mean) @ whiten
    d = np.sqrt(np.einsum("ij,ij->i", z, z))
    return {"method": "mahalanobis (standardized features, ridge-regularized covariance)",
            "mean": mean.tolist(), "whiten": whiten.tolist(), "threshold": float(np.quantile(d, quantile)),
            "quantile": float(quantile), "n_train": len(X),
            "widening": "outside (distance > threshold) U is multiplied by distance / threshold"}


def predict_clouds(ms: ModelSet, X: np.ndarray, cloud_id: np.ndarray, with_u: bool = True,
                   surface_class: np.ndarray | None = None, noise: np.ndarray | None = None
                   ) -> dict[str, np.ndarray]:
    """Published predictions for rows of several clouds, each cloud on its own (its rows form the sets, in row
    order); U with ``surface_class`` (the rows' classes) per class when the card is calibrated so, and with
    ``noise`` (the rows' measured noise) where the card's U takes it. Returns errors, sigma (and U, out_of_domain,
    domain_distance with ``with_u``), rows aligned with X."""
    X = np.asarray(X, np.float32)
    cid = np.asarray(cloud_id)
    out: dict[str, np.ndarray] = {"errors": np.full((len(X), 3), np.nan), "sigma": np.full((len(X), 3), np.nan)}
    if with_u:
        out.update(U=np.full((len(X), 3), np.nan), out_of_domain=np.zeros(len(X), bool),
                   domain_distance=np.full(len(X), np.nan))
    for c in np.unique(cid):
        rows = np.flatnonzero(cid == c)
        cls = None if surface_class is None else np.asarray(surface_class)[rows]
        nz = None if noise is None else np.asarray(noise)[rows]
        if with_u:
            r = ms.predict_with_uncertainty(X[rows], surface_class=cls, noise=nz)
            out["errors"][rows], out["sigma"][rows], out["U"][rows] = r.errors, r.sigma, r.U
            out["out_of_domain"][rows], out["domain_distance"][rows] = r.out_of_domain, r.domain_distance
        else:
            out["errors"][rows], out["sigma"][rows] = ms.predict_with_sigma(X[rows])
    return out


def cross_conformal_by_cloud(y: np.ndarray, pred: np.ndarray, sigma: np.ndarray, cloud_id: np.ndarray,
                             confidence: float = 0.95, seed: int = 0,
                             sigma_floor_mm: float = SIGMA_FLOOR_MM) -> dict[str, dict[str, float]]:
    """Coverage and mean width of the calibrated intervals on clouds the model never saw, for the study tables:
    the clouds are split in two halves BY CLOUD (seeded); each half is calibrated on the other (split-conformal,
    :func:`conformal_multiplier`) and judged; the hits and widths of both halves are pooled. Per axis: coverage,
    mean_width_mm (2U), multiplier (mean of the two). Rows with an identically zero target are left out."""
    cid = np.asarray(cloud_id)
    clouds = np.unique(cid)
    if len(clouds) < 2:
        raise ValueError("cross-conformal calibration needs at least two held-out clouds")
    half = np.isin(cid, np.random.default_rng(seed).permutation(clouds)[: len(clouds) // 2])
    out = {}
    for a, ax in enumerate(AXES):
        ok = np.isfinite(y[:, a]) & np.isfinite(pred[:, a]) & np.isfinite(sigma[:, a]) & (y[:, a] != 0.0)
        r = np.abs(y[:, a] - pred[:, a])
        sg = sigma[:, a] + sigma_floor_mm
        hits, widths, ks = [], [], []
        for cal in (half, ~half):
            c, t = ok & cal, ok & ~cal
            k = conformal_multiplier(r[c], sg[c], confidence)
            hits.append(r[t] <= k * sg[t])
            widths.append(2 * k * sg[t])
            ks.append(k)
        out[ax] = {"coverage": float(np.concatenate(hits).mean()),
                   "mean_width_mm": float(np.concatenate(widths).mean()), "multiplier": float(np.mean(ks))}
    return out


def _own_multipliers(cell: np.ndarray, n_cells: int, res: np.ndarray, sig: np.ndarray, ok: np.ndarray,
                     confidence: float) -> tuple[list, list]:
    """(multipliers, counts), cell → [x, y, z], of the rows in each condition ``cell`` (M,); None where a cell has
    fewer than MIN_POINTS usable rows on an axis."""
    mult: list[list[float | None]] = []
    counts: list[list[int]] = []
    for c in range(n_cells):
        row_m: list[float | None] = []
        row_n: list[int] = []
        for a in range(3):
            m = ok[:, a] & (cell == c)
            k = int(m.sum())
            row_n.append(k)
            row_m.append(conformal_multiplier(res[m, a], sig[m, a], confidence) if k >= MIN_POINTS else None)
        mult.append(row_m)
        counts.append(row_n)
    return mult, counts


def _envelope(own: list, n_cells: int, n_inc: int, envelope: int) -> list:
    """Each cell's multiplier: the largest of its own and those of the ``envelope`` incidence bins on either side
    (same exposure); None stays None."""
    mult = [list(r) for r in own]
    ne = n_cells // n_inc
    for c in range(n_cells):
        i, e = divmod(c, ne)
        for a in range(3):
            if own[c][a] is None:
                continue
            near = [own[j * ne + e][a] for j in range(max(0, i - envelope), min(n_inc, i + envelope + 1))]
            mult[c][a] = max(m for m in near if m is not None)
    return mult


def _cell_multipliers(cell: np.ndarray, n_cells: int, n_inc: int, res: np.ndarray, sig: np.ndarray, ok: np.ndarray,
                      confidence: float, envelope: int, groups: np.ndarray | None = None) -> tuple[list, list, list]:
    """(multipliers after the incidence envelope, own multipliers, counts), cell → [x, y, z], of the rows in each
    condition ``cell`` (M,); None where a cell has fewer than MIN_POINTS usable rows on an axis. ``groups`` (M, 3)
    bool: a cell's own multiplier on an axis is also at least that of its rows where ``groups`` is True and that of
    the others, each with MIN_POINTS rows or more (every such subgroup covered at ``confidence``)."""
    own, counts = _own_multipliers(cell, n_cells, res, sig, ok, confidence)
    if groups is not None:
        for g in (groups, ~groups):
            sub, _ = _own_multipliers(cell, n_cells, res, sig, ok & g, confidence)
            own = [[o if s is None else (s if o is None else max(o, s)) for o, s in zip(ro, rs, strict=True)]
                   for ro, rs in zip(own, sub, strict=True)]
    return _envelope(own, n_cells, n_inc, envelope), own, counts


def conditional_multipliers(X: np.ndarray, feature_names: list[str], res: np.ndarray, sig: np.ndarray,
                            ok: np.ndarray, confidence: float = 0.95, envelope: int = ENVELOPE_BINS,
                            incidence_edges: tuple[float, ...] = INCIDENCE_EDGES_DEG,
                            surface_class: np.ndarray | None = None, surface_sigma: np.ndarray | None = None,
                            noise_block: dict[str, Any] | None = None, by_source: bool = False
                            ) -> dict[str, Any] | None:
    """Mondrian split-conformal multipliers per calibration condition (judge/conditions.py: incidence 10° bins ×
    the exposure levels of the calibration rows): ``{"incidence_edges_deg", "exposure_edges_ms", "multiplier"
    (cell → [x, y, z] or None), "n" (cell → points per axis), "min_points"}``; None when the features lack Inc
    or exposure_time. ``res`` (M, 3) residuals y − ŷ, ``sig`` (M, 3) σ̂ + floor, ``ok`` (M, 3) usable rows per axis.
    A cell with fewer than MIN_POINTS usable points on an axis gets None there: no U for such points.

    ``envelope``: a cell's multiplier is the largest of its own and those of the ``envelope`` incidence bins on
    either side (same exposure). The spread of an axis' error at a given incidence depends on the artifact's
    curvature too (near normal incidence the x error of a sphere is a tiny projection): a cell calibrated on the
    campaign's shapes alone covered 91 % of new shapes' points at 0-10° (x), its neighbours' maximum 97 %.

    ``surface_class`` (M,) int (judge/surface_class.py, −1: none): the same multipliers per surface class as well
    (block ``by_surface``; a class's cell with too few points is None there and takes the all-class cell's).
    ``surface_sigma`` (M, 3): the σ (+ floor) the per-class multipliers are calibrated on instead of ``sig`` (max(σ̂,
    measured noise·|N|), :func:`calibrate`), described by ``noise_block`` (block ``by_surface.noise``); the
    all-class ones stay on ``sig`` (σ̂: unorganized scans, the recommender). ``by_source`` (with ``surface_sigma``):
    a class's cell multiplier on an axis covers its rows where the noise term is the larger and those where σ̂ is,
    each group on its own (the largest of the pooled and the two groups' multipliers; ``by_surface.sources``)."""
    if not set(CONDITION_FEATURES) <= set(feature_names):
        return None
    exp = np.asarray(X[:, list(feature_names).index("exposure_time")], np.float64)
    levels = np.unique(exp[np.isfinite(exp)])
    if len(levels) > 6:  # a continuous range of exposures: three bins of equal counts
        levels = np.quantile(exp[np.isfinite(exp)], [1 / 6, 1 / 2, 5 / 6])
    ie, ee = [float(a) for a in incidence_edges], exposure_edges(levels)
    cell = condition_index(X, feature_names, ie, ee)
    n_inc = len(ie) - 1
    n_cells = n_inc * (len(ee) - 1)
    mult, own, counts = _cell_multipliers(cell, n_cells, n_inc, res, sig, ok, confidence, envelope)
    out = {"by": "incidence angle acos(Inc) in 10 deg bins x exposure_time levels (Mondrian conformal)",
           "incidence_edges_deg": ie, "exposure_edges_ms": ee, "exposure_levels_ms": levels.tolist(),
           "multiplier": mult, "own_multiplier": own, "envelope_bins": int(envelope), "n": counts,
           "min_points": MIN_POINTS,
           "cell": "incidence bin * (len(exposure_edges_ms) - 1) + exposure bin"}
    if surface_class is not None:
        from ..judge.surface_class import FLAT_CURVATURE_PER_MM, SHARP_CURVATURE_PER_MM, SURFACE_CLASSES
        from ..preprocess.curvature import RADIUS_MM

        cls = np.asarray(surface_class, np.int64)
        sig_s = sig if surface_sigma is None else surface_sigma
        # by_source: σ comes from two sources (max of σ̂ and the measured noise) and each source's rows of a cell
        # are covered on their own. Pooled, on the pose model's calibration (its head poses) the rows where the noise
        # overstates the error (tilted plates) pulled the multiplier of those where σ̂ is the larger term below
        # what they need (a flat top seen from a tilted head); on the primary's (looking down) it was not needed
        # and costs sharpness (docs/uncertainty.md)
        groups = np.asarray(surface_sigma) > np.asarray(sig) if by_source and surface_sigma is not None else None
        per = [_cell_multipliers(np.where(cls == k, cell, -1), n_cells, n_inc, res, sig_s, ok, confidence, envelope,
                                 groups) for k in range(len(SURFACE_CLASSES))]
        out["by_surface"] = {
            "classes": list(SURFACE_CLASSES), "flat_curvature_per_mm": FLAT_CURVATURE_PER_MM,
            "sharp_curvature_per_mm": SHARP_CURVATURE_PER_MM, "radius_mm": RADIUS_MM,
            "measure": "principal curvatures from normals radius_mm apart on the scan grid "
                       "(xmetro_ros.preprocess.curvature, xmetro_ros.judge.surface_class)",
            "multiplier": [p[0] for p in per], "own_multiplier": [p[1] for p in per], "n": [p[2] for p in per],
            "fallback": "a class's condition with fewer than min_points points (None) takes the all-class multiplier"}
        if noise_block:
            out["by_surface"]["noise"] = noise_block
        if groups is not None:
            out["by_surface"]["sources"] = (
                "each cell's own multiplier covers, on each axis, its rows where the measured noise is the larger "
                "term of sigma and those where sigma_hat is, each group with min_points rows or more (the largest "
                "of the pooled and the groups' multipliers)")
    return out


def calibrate(model_dir: str | Path, X: np.ndarray, y: np.ndarray, cloud_id: np.ndarray,
              confidence: float = 0.95, cloud_labels: list | None = None, write: bool = True,
              sigma_floor_mm: float = SIGMA_FLOOR_MM, conditional: bool = True,
              envelope: int = ENVELOPE_BINS, surface_class: np.ndarray | None = None,
              noise: np.ndarray | None = None, by_source: bool = False, along_normal: bool = False,
              tilt: np.ndarray | None = None) -> dict[str, Any]:
    """Split-conformal calibration of the model set in ``model_dir`` on calibration clouds (rows X (M, F),
    measured errors y (M, 3) mm, cloud ids): writes the card's ``uncertainty`` block (unless ``write`` False) and
    returns it. The clouds must be held out from training (the caller's split; their ids / labels are recorded).
    ``conditional``: also one multiplier per calibration condition (incidence × exposure, the block's
    ``conditional`` part, :func:`conditional_multipliers` with ``envelope``), which U then uses; with
    ``surface_class`` (M,) (the rows' classes, judge/surface_class.py) per condition and surface class as well;
    with ``noise`` (M,) (the rows' measured noise, mm along the normal, NaN: none; preprocess/noise.py) those per
    class on max(σ̂, noise·|N|) (:mod:`xmetro_ros.judge.measured_noise`), the σ the judge then multiplies;
    ``by_source``: each σ source's rows of a class's cell covered on their own (:func:`conditional_multipliers`).
    ``along_normal`` (with ``surface_class``, ``noise`` and ``tilt`` (M, 3), the rows' measured tilt noise,
    preprocess/tilt_noise.py): the block also gets ``along_normal``, d and U carried onto the measured normal with U
    along it from the measured noise (:mod:`xmetro_ros.judge.along_normal`, fitted by
    :func:`.along_normal.fit_rows` on the same rows and predictions).
    """
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    ms = ModelSet.load(model_dir)
    ms.log_sigma_max = None  # a previous calibration's σ̂ ceiling must not shape this one
    y = np.asarray(y, np.float64)
    pred = predict_clouds(ms, X, cloud_id, with_u=False)
    mult, achieved, n = [], [], []
    oks = np.zeros(y.shape, bool)
    for a in range(3):
        ok = np.isfinite(y[:, a]) & np.isfinite(pred["errors"][:, a]) & (pred["sigma"][:, a] > 0)
        ok &= y[:, a] != 0.0  # identically zero by construction (see the module doc)
        oks[:, a] = ok
        if ok.sum() < 1 / (1 - confidence):
            raise ValueError(f"{int(ok.sum())} calibration points on axis {AXES[a]}: too few for {confidence:g}")
        res = y[ok, a] - pred["errors"][ok, a]
        sig = pred["sigma"][ok, a] + sigma_floor_mm
        k = conformal_multiplier(res, sig, confidence)
        mult.append(k)
        achieved.append(float(np.mean(np.abs(res) <= k * sig)))
        n.append(int(ok.sum()))
    ids = np.unique(np.asarray(cloud_id)).tolist()
    block = {
        "method": "split-conformal (crepes ConformalRegressor, normalized scores |y - yhat| / sigma_hat), "
                  "calibration clouds held out from training by cloud",
        "confidence": float(confidence),
        "multiplier": mult,
        "sigma_floor_mm": float(sigma_floor_mm),
        "U": "multiplier[axis] * (sigma_hat + sigma_floor_mm), times distance/threshold outside domain_mv",
        # σ̂ is trusted up to the largest value the calibration saw; beyond it the domain distance widens U
        "sigma_max_mm": [float(np.nanmax(pred["sigma"][:, a])) for a in range(3)],
        "sigma_source": {AXES[a]: ("log_sigma output" if any(m.sigma and a in m.axes for m in ms.members)
                                   else "constant 1 mm (absolute residuals)") for a in range(3)},
        "calibration_clouds": cloud_labels if cloud_labels is not None else ids,
        "n_calibration_points": n,
        "achieved_coverage_calibration": dict(zip(AXES, achieved, strict=True)),
    }
    if conditional:
        names = list(ms.feature_names)
        cls, surf_sig, nblock = surface_class, None, None
        if surface_class is not None and noise is not None and set(NORMAL_FEATURES) <= set(names):
            s_eff, cls = effective_sigma(pred["sigma"], np.asarray(X)[:, [names.index(c) for c in NORMAL_FEATURES]],
                                         surface_class, noise)
            surf_sig = s_eff + sigma_floor_mm
            nblock = {"sigma": "max(sigma_hat, noise * |N_axis|) + sigma_floor_mm for points with a measured noise "
                               "and a class; sigma_hat + sigma_floor_mm and the all-class multiplier for the others",
                      "measure": "mean |second difference along the laser line . normal| / sqrt(6) over "
                                 "window_cells^2 grid cells x sqrt(pi/2) (xmetro_ros.preprocess.noise)",
                      "window_cells": NOISE_WINDOW, "min_samples": NOISE_MIN_SAMPLES,
                      "rows_with_noise": int(np.isfinite(np.asarray(noise, np.float64)).sum())}
        cond = conditional_multipliers(np.asarray(X), names, y - pred["errors"],
                                       pred["sigma"] + sigma_floor_mm, oks, confidence, envelope=envelope,
                                       surface_class=cls, surface_sigma=surf_sig, noise_block=nblock,
                                       by_source=by_source)
        if cond is not None:
            block["conditional"] = cond
            block["U"] = ("multiplier of the point's condition (conditional: incidence bin x exposure level"
                          + (" x surface class" if "by_surface" in cond else "") + "; none: "
                          "no U) * (sigma_hat + sigma_floor_mm"
                          + ("; max(sigma_hat, measured noise * |N_axis|) + sigma_floor_mm for a point with a class "
                             "and a measured noise" if nblock else "")
                          + "), times distance/threshold outside domain_mv")
    if along_normal:
        if surface_class is None or noise is None or tilt is None:
            raise ValueError("along_normal needs the rows' surface classes, measured noise and tilt noise")
        from ..judge.conditions import exposure_edges
        from ..judge.surface_class import SURFACE_CLASSES
        from .along_normal import fit_rows

        names = list(ms.feature_names)
        levels = sorted({float(v) for v in np.asarray(X)[:, names.index("exposure_time")]})
        an = fit_rows(np.asarray(X), names, y, pred["errors"], surface_class, noise,
                      np.asarray(exposure_edges(levels)[1:-1]), len(SURFACE_CLASSES), confidence, tilt=tilt)
        block["along_normal"] = {**an.to_block(), "fitted_on": "the calibration rows with a measured noise and a "
                                 "surface class, the model's predictions of this calibration"}
    if write:
        update_card(model_dir, uncertainty=block)
    return block


def _spearman(a: np.ndarray, b: np.ndarray) -> float:
    from scipy.stats import spearmanr

    return float(spearmanr(a, b).statistic)


def interval_metrics(errors: np.ndarray, U: np.ndarray, y: np.ndarray, oracle_std: np.ndarray | None = None,
                     bins: dict[str, tuple[np.ndarray, np.ndarray]] | None = None, z: float = 1.96) -> dict:
    """Per axis: coverage of errors ± U over the measured errors y, mean U, mean width (2U); with the oracle std:
    mean U / mean oracle half-width (z · std; the sharpness ratio) and the Spearman rank correlation of U with
    the true std; points where the true std is 0 (no random error on that axis) are left out.
    ``bins``: name → (values (M,), edges): coverage per bin (conditional coverage)."""
    err, U, y = (np.asarray(v, np.float64) for v in (errors, U, y))
    out: dict[str, Any] = {}
    for a, ax in enumerate(AXES):
        ok = np.isfinite(err[:, a]) & np.isfinite(U[:, a]) & np.isfinite(y[:, a])
        if oracle_std is not None:  # axes with a true spread (not the identically-zero axial error of a cylinder)
            ok &= np.isfinite(oracle_std[:, a]) & (oracle_std[:, a] > 0)
        if not ok.any():
            out[ax] = {"n": 0}
            continue
        hit = np.abs(y[ok, a] - err[ok, a]) <= U[ok, a]
        m: dict[str, Any] = {"n": int(ok.sum()), "coverage": float(hit.mean()), "mean_U": float(U[ok, a].mean()),
                             "mean_width": float(2 * U[ok, a].mean())}
        if oracle_std is not None:
            s = oracle_std[ok, a]
            m["mean_oracle_half_width"] = float(z * s.mean())
            ho = m["mean_oracle_half_width"]
            m["sharpness_ratio"] = m["mean_U"] / ho if ho > 0 else float("nan")
            m["spearman_U_true_std"] = _spearman(U[ok, a], s) if np.ptp(s) > 0 else float("nan")
        if bins:
            m["bins"] = {}
            for name, (vals, edges) in bins.items():
                v = np.asarray(vals, np.float64)[ok]
                k = np.digitize(v, edges[1:-1])
                m["bins"][name] = [
                    {"lo": float(edges[i]), "hi": float(edges[i + 1]), "n": int((k == i).sum()),
                     "coverage": float(hit[k == i].mean()) if (k == i).any() else None}
                    for i in range(len(edges) - 1)]
        out[ax] = m
    return out
