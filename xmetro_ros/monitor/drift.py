"""Drift detection on reference-artifact scans re-scanned in the cell (ROS-free core; docs/closed-loop.md).

A cell re-scans a reference artifact (a sphere in the fixture) every so often. For each such *reference scan* the
caller gives, per point, the actual error and the model's prediction in one sign (mm; the node's reference check
gives both as published deviations, measured − nominal) and, when the model gives one, the half-width U of its
interval (mm, prediction ± U). ``DriftMonitor.update`` reduces the scan to three
statistics and tracks each over the stream of reference scans:

- ``residual_mean``: mean of the residual r = actual − predicted (a bias the model does not predict);
- ``residual_rms``: log of the RMS of r (a new effect adds variance even when its mean is zero);
- ``coverage``: fraction of points with |r| ≤ U (only when U is given; a drifting scanner leaves its intervals).

Residuals given as (N, 3) are reduced along ``normals`` when given, else per component (all 3N values); coverage
is counted per axis when U is given per axis (N, 3) (the interval is per axis), along the normal when U has one
value per point.

In-control level and spread: each statistic's median and scaled MAD over the first ``warmup`` reference scans
(or a ``baseline`` given by the caller, e.g. from the calibration campaign), with a floor on the spread. Then two
standard detectors per statistic on the standardised value z = (x − μ0) / σ0 (Montgomery, *Introduction to
Statistical Quality Control*, ch. 9):

- EWMA: e_t = λ z_t + (1 − λ) e_{t−1}, alarm when |e_t| > L · sqrt(λ / (2 − λ) · (1 − (1 − λ)^{2t}));
- CUSUM (two-sided): S⁺ = max(0, S⁺ + z − k), S⁻ = max(0, S⁻ − z − k), alarm when S⁺ or S⁻ > h.

Coverage is one-sided (only a *drop* of coverage alarms; the RMS only alarms upward; the mean both ways).
Defaults (λ 0.2, L 3.5, k 0.5, h 6, 10-scan warm-up): on simulated reference scans, 1 false alarm in 200 stable
streams of 60 reference scans (0.5 %; L 3, h 5: 1.5 %), and a 4 µm ripple (the size of the noise) switched on
mid-stream raised WARN 1-2 reference scans later (test/test_drift.py asserts ≤ 3 % and ≤ 3 scans; figures in
docs/closed-loop.md). The state is ``WARMUP`` until the in-control level is known, then ``OK`` or ``WARN`` (the
statistic and detector that fired, its value and threshold); WARN holds until ``reset``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["STATISTICS", "DriftConfig", "DriftMonitor", "DriftState", "scan_statistics"]

#: statistic name → alarm direction (+1 up only, −1 down only, 0 both)
STATISTICS = {"residual_mean": 0, "residual_rms": +1, "coverage": -1}


@dataclass(frozen=True)
class DriftConfig:
    """Detector parameters (see the module docstring)."""

    warmup: int = 10
    lam: float = 0.2
    L: float = 3.5
    k: float = 0.5
    h: float = 6.0
    #: floors of the in-control spread per statistic (mm for the mean, log-ratio for the RMS, fraction for coverage):
    #: a warm-up of a few very similar scans must not make the detector hair-triggered.
    min_sigma: tuple[float, float, float] = (0.0005, 0.03, 0.01)


@dataclass
class DriftState:
    """What the monitor says after a reference scan."""

    state: str  # "WARMUP" | "OK" | "WARN"
    n_scans: int
    statistic: str = ""  # the statistic that raised WARN
    detector: str = ""  # "ewma" | "cusum"
    value: float = 0.0  # the detector's value (standardised units)
    threshold: float = 0.0
    first_warn_scan: int | None = None  # 1-based index of the reference scan that first raised WARN
    stats: dict[str, float] = field(default_factory=dict)  # this scan's statistics
    detectors: dict[str, dict[str, float]] = field(default_factory=dict)  # per statistic: ewma, cusum_pos, cusum_neg

    @property
    def message(self) -> str:
        """One line for /diagnostics."""
        if self.state == "WARN":
            return (f"drift: {self.statistic} {self.detector} {self.value:.2f} > {self.threshold:.2f} "
                    f"(since reference scan {self.first_warn_scan})")
        if self.state == "WARMUP":
            return f"warming up: {self.n_scans} reference scans"
        return f"ok: {self.n_scans} reference scans"

    def to_dict(self) -> dict[str, Any]:
        """JSON-able state."""
        return {"state": self.state, "n_scans": self.n_scans, "statistic": self.statistic, "detector": self.detector,
                "value": self.value, "threshold": self.threshold, "first_warn_scan": self.first_warn_scan,
                "stats": dict(self.stats), "detectors": {k: dict(v) for k, v in self.detectors.items()},
                "message": self.message}


def scan_statistics(actual: np.ndarray, predicted: np.ndarray, U: np.ndarray | None = None,
                    normals: np.ndarray | None = None) -> dict[str, float]:
    """The statistics of one reference scan (mm; see the module docstring). Non-finite points are ignored."""
    a = np.asarray(actual, dtype=float)
    p = np.asarray(predicted, dtype=float)
    if a.shape != p.shape:
        raise ValueError(f"actual {a.shape} and predicted {p.shape} differ in shape")
    r = a - p
    u = None if U is None else np.asarray(U, dtype=float)
    if r.ndim == 2 and normals is not None:
        n = np.asarray(normals, dtype=float)
        if n.shape != r.shape:
            raise ValueError(f"normals {n.shape} must match the residual {r.shape}")
        res = np.einsum("ij,ij->i", r, n)
        # Coverage is judged where the interval is defined: per axis when U is per axis (the conformal guarantee is
        # per axis, and a per-axis half-width has no signed projection onto the normal), else along the normal.
        cov = r if u is not None and u.ndim == 2 else res
    else:
        res = cov = r
    # One row per point: a point counts when its residual, and its interval when U is given, are finite.
    res2 = res.reshape(len(res), -1)
    ok = np.isfinite(res2).all(axis=1)
    if u is not None:
        cov2 = cov.reshape(len(res2), -1)
        try:
            u2 = np.broadcast_to(u.reshape(len(res2), -1) if u.ndim else u, cov2.shape)
        except ValueError as e:
            raise ValueError(f"U has {u.size} values for {cov2.size} residuals") from e
        ok &= np.isfinite(cov2).all(axis=1) & np.isfinite(u2).all(axis=1)
    if ok.sum() < 3:
        raise ValueError("a reference scan needs at least 3 finite residuals")
    rr = res2[ok]
    out = {"residual_mean": float(rr.mean()), "residual_rms": float(np.log(max(np.sqrt((rr**2).mean()), 1e-12)))}
    if u is not None:
        out["coverage"] = float(np.mean(np.abs(cov2[ok]) <= u2[ok]))
    return out


class DriftMonitor:
    """EWMA + CUSUM drift detector over reference scans. ``update(actual, predicted, U=None)`` → DriftState.

    Args:
        cfg: thresholds.
        baseline: in-control ``{statistic: (level, sigma)}`` known beforehand (no warm-up then for those given).
    """

    def __init__(self, cfg: DriftConfig | None = None,
                 baseline: dict[str, tuple[float, float]] | None = None) -> None:
        self.cfg = cfg or DriftConfig()
        self._given = dict(baseline or {})
        self.reset()

    def reset(self) -> None:
        """Forget the stream (after a fix or a re-calibration); a given baseline is kept."""
        self.n = 0
        self._history: dict[str, list[float]] = {k: [] for k in STATISTICS}
        self._base: dict[str, tuple[float, float]] = dict(self._given)
        self._ewma: dict[str, float] = {}
        self._cpos: dict[str, float] = {}
        self._cneg: dict[str, float] = {}
        self._t: dict[str, int] = {}
        self._warn: DriftState | None = None

    @property
    def baseline(self) -> dict[str, tuple[float, float]]:
        """In-control (level, sigma) per statistic once known."""
        return dict(self._base)

    def update(self, actual: np.ndarray, predicted: np.ndarray, U: np.ndarray | None = None,
               normals: np.ndarray | None = None) -> DriftState:
        """Add one reference scan (per-point arrays, mm) and return the monitor's state."""
        stats = scan_statistics(actual, predicted, U, normals)
        return self.update_stats(stats)

    def update_stats(self, stats: dict[str, float]) -> DriftState:
        """Add one reference scan given by its statistics (``scan_statistics``)."""
        cfg = self.cfg
        self.n += 1
        dets: dict[str, dict[str, float]] = {}
        fired: list[tuple[float, str, str, float, float]] = []
        for si, (name, direction) in enumerate(STATISTICS.items()):
            if name not in stats:
                continue
            x = float(stats[name])
            if name not in self._base:
                self._history[name].append(x)
                if len(self._history[name]) >= cfg.warmup:
                    h = np.asarray(self._history[name])
                    med = float(np.median(h))
                    mad = 1.4826 * float(np.median(np.abs(h - med)))
                    self._base[name] = (med, max(mad, float(h.std(ddof=1)) if len(h) > 1 else 0.0,
                                             cfg.min_sigma[si]))
                continue
            mu, sd = self._base[name]
            z = (x - mu) / max(sd, cfg.min_sigma[si])
            t = self._t.get(name, 0) + 1
            self._t[name] = t
            e = cfg.lam * z + (1 - cfg.lam) * self._ewma.get(name, 0.0)
            self._ewma[name] = e
            cp = max(0.0, self._cpos.get(name, 0.0) + z - cfg.k)
            cn = max(0.0, self._cneg.get(name, 0.0) - z - cfg.k)
            self._cpos[name], self._cneg[name] = cp, cn
            lim = cfg.L * np.sqrt(cfg.lam / (2 - cfg.lam) * (1 - (1 - cfg.lam) ** (2 * t)))
            dets[name] = {"z": z, "ewma": e, "ewma_limit": float(lim), "cusum_pos": cp, "cusum_neg": cn}
            ew = e if direction > 0 else (-e if direction < 0 else abs(e))
            cu = cp if direction > 0 else (cn if direction < 0 else max(cp, cn))
            if ew > lim:
                fired.append((ew / lim, name, "ewma", float(e), float(lim)))
            if cu > cfg.h:
                fired.append((cu / cfg.h, name, "cusum", float(cu), float(cfg.h)))
        ready = all(n in self._base for n in stats)
        if self._warn is None and fired:
            _, name, det, val, thr = max(fired)
            self._warn = DriftState("WARN", self.n, name, det, val, thr, first_warn_scan=self.n)
        if self._warn is not None:
            w = self._warn
            return DriftState("WARN", self.n, w.statistic, w.detector, w.value, w.threshold, w.first_warn_scan,
                              stats=dict(stats), detectors=dets)
        return DriftState("OK" if ready else "WARMUP", self.n, stats=dict(stats), detectors=dets)
