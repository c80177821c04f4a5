"""In-line monitoring on reference scans (ROS-free core; docs/closed-loop.md, "In-line monitoring in the node").

A cell re-scans a reference artifact — a certified sphere in a fixture — every so often. For each such *reference
scan* judged by the node, :class:`ReferenceChecker` compares, point by point, the **actual** deviation (measured −
nominal against the certified sphere, mm, scan frame: the sign the node publishes, ``scan.targets``'
``published_deviation``) with the model's prediction in that sign and its interval U, and feeds
the per-scan statistics to a :class:`xmetro_ros.monitor.drift.DriftMonitor` (EWMA + CUSUM on the residual's mean and
RMS and
on interval coverage). When the monitor says WARN, a screening names the candidate variable most associated with
the residual on that scan (the "candidate effect"): Spearman's rank correlation of the residual along the normal
with each candidate a live node can compute (profile time ``t``, position along the line ``u``, ``intensity``,
incidence and view angles, stand-off, scan-frame position), Holm-adjusted over the candidates. It is a screening of
one scan; ``xmetro loop`` on the recorded reference scans is the trace proper (held-out clouds, permutation tests).

The sphere's position is either known (fixture, CMM: ``center_mm``) or fitted on each scan with the certified
radius (``fit_center``). A fitted position absorbs every error that looks like a shift of the sphere: a pose or
stand-off drift of the scanner is then invisible to the monitor (documented consequence). A scan whose points do
not fit the declared sphere (the wrong artifact, a wrong position: median |normal error| over ``max_mismatch_mm``)
gives ``MISMATCH`` and is not fed to the monitor. Spurious returns that the outlier filter left (residuals beyond
``TRIM_SIGMA`` robust standard deviations) are left out of the statistics and counted.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.stats import spearmanr

from ..scan.artifacts import Sphere
from ..scan.targets import FitError, errors_with_fit, published_deviation
from .drift import DriftConfig, DriftMonitor, DriftState

__all__ = ["CANDIDATE_ALPHA", "CANDIDATE_MIN_RHO", "ReferenceChecker", "ReferenceResult", "ReferenceSpec",
           "live_candidates", "screen_candidates"]

#: Holm-adjusted p-value below which a candidate is named.
CANDIDATE_ALPHA = 0.01
#: ... and the smallest |Spearman ρ| worth naming (with 10⁴ points a ρ of 0.03 is already "significant").
CANDIDATE_MIN_RHO = 0.1
#: Residuals beyond this many robust standard deviations (1.4826 MAD) are spurious returns, not drift.
TRIM_SIGMA = 8.0
#: Points used by the screening (evenly spaced subsample: its cost must not grow with the scan).
SCREEN_MAX_POINTS = 20_000


@dataclass(frozen=True)
class ReferenceSpec:
    """The reference artifact: a certified sphere (radius mm) at a known centre (scan frame, mm) or fitted."""

    radius_mm: float
    center_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    fit_center: bool = False
    #: median |normal error| (mm) above which the scan does not show this sphere where declared
    max_mismatch_mm: float = 0.5

    def __post_init__(self) -> None:
        if not (np.isfinite(self.radius_mm) and self.radius_mm > 0):
            raise ValueError(f"reference radius must be positive, got {self.radius_mm}")
        if len(self.center_mm) != 3 or not np.all(np.isfinite(self.center_mm)):
            raise ValueError(f"reference centre must be 3 finite coordinates, got {self.center_mm}")
        if not (np.isfinite(self.max_mismatch_mm) and self.max_mismatch_mm > 0):
            raise ValueError(f"max_mismatch_mm must be positive, got {self.max_mismatch_mm}")

    @property
    def sphere(self) -> Sphere:
        return Sphere(float(self.radius_mm), (float(self.center_mm[0]), float(self.center_mm[1]),
                                               float(self.center_mm[2])))


@dataclass
class ReferenceResult:
    """One reference scan checked. Lengths in mm; ``coverage`` NaN when the model gives no U."""

    state: str  # "WARMUP" | "OK" | "WARN" | "MISMATCH"
    reference_scans: int  # scans fed to the monitor so far
    points: int  # points compared (after the trim)
    actual_mean_abs_mm: float = float("nan")  # mean |actual error along the normal|
    residual_mean_mm: float = float("nan")  # mean of (actual − predicted) along the normal
    residual_rms_mm: float = float("nan")
    coverage: float = float("nan")  # share of points with |residual| ≤ U along the normal
    drift: DriftState | None = None
    candidate: str = ""  # WARN: the candidate variable named by the screening ("" = none)
    candidate_rho: float = float("nan")
    candidate_p: float = float("nan")
    screening: dict[str, dict[str, float]] = field(default_factory=dict)  # every candidate: rho, p (Holm)
    trimmed: int = 0  # points left out as spurious (beyond TRIM_SIGMA robust std of the residual)
    message: str = ""


def screen_candidates(residual: np.ndarray, candidates: dict[str, np.ndarray],
                      max_points: int = SCREEN_MAX_POINTS) -> dict[str, dict[str, float]]:
    """Spearman ρ and Holm-adjusted p of ``residual`` (M,) against each candidate (M,), on at most ``max_points``
    evenly spaced points with every value finite. Constant candidates are left out."""
    r = np.asarray(residual, dtype=float)
    sel = np.flatnonzero(np.isfinite(r))
    if len(sel) > max_points:
        sel = sel[np.linspace(0, len(sel) - 1, max_points).astype(np.int64)]
    out: dict[str, dict[str, float]] = {}
    for name, v in candidates.items():
        x = np.asarray(v, dtype=float)
        if x.shape != r.shape:
            continue
        s = sel[np.isfinite(x[sel])]
        if len(s) < 10 or np.ptp(x[s]) == 0:
            continue
        res = spearmanr(r[s], x[s])
        rho, p = float(res.statistic), float(res.pvalue)
        if np.isfinite(rho):
            out[name] = {"rho": rho, "p": p}
    if out:
        names = list(out)
        ps = np.array([out[n]["p"] for n in names])
        order = np.argsort(ps)
        adj = np.minimum(1.0, np.maximum.accumulate(ps[order] * (len(ps) - np.arange(len(ps)))))
        for k, i in enumerate(order):
            out[names[i]]["p"] = float(adj[k])
    return out


class ReferenceChecker:
    """Checks reference scans against their certified sphere and tracks drift (see the module docstring).

    Args:
        spec: the reference sphere.
        cfg: the drift detector's parameters (warm-up, EWMA / CUSUM thresholds).
    """

    def __init__(self, spec: ReferenceSpec, cfg: DriftConfig | None = None) -> None:
        self.spec = spec
        self.monitor = DriftMonitor(cfg)

    def reset(self) -> None:
        """Forget the stream (after a fix or a re-calibration): the next scans learn the in-control level anew."""
        self.monitor.reset()

    def check(self, points_mm: np.ndarray, predicted_mm: np.ndarray, U_mm: np.ndarray | None,
              candidates: dict[str, np.ndarray] | Callable[[], dict[str, np.ndarray]] | None = None
              ) -> ReferenceResult:
        """Check one reference scan; the residual is taken along the certified sphere's normal.

        Args:
            points_mm: (M, 3) measured points (scan frame, mm) that the model judged.
            predicted_mm: (M, 3) the model's predictions, its target nominal − measured per axis (NaN rows: no
                prediction); actual and predicted are compared, and the residual reported, as published
                deviations (measured − nominal).
            U_mm: (M, 3) expanded uncertainty per axis, or None (model without calibration).
            candidates: {name: (M,)} variables for the screening on WARN, or a callable giving them (computed only
                on WARN, e.g. ``lambda: live_candidates(prepared)``).
        """
        p = np.asarray(points_mm, dtype=np.float64)
        pred = np.asarray(predicted_mm, dtype=np.float64)
        ok = np.isfinite(p).all(axis=1) & np.isfinite(pred).all(axis=1)
        n_ok = int(ok.sum())
        n_mon = self.monitor.n
        if n_ok < 3:
            return ReferenceResult("MISMATCH", n_mon, n_ok, message=f"reference scan: only {n_ok} predicted points")
        try:
            target, used = errors_with_fit(p[ok], self.spec.sphere, self.spec.fit_center)
        except (FitError, ValueError) as e:
            return ReferenceResult("MISMATCH", n_mon, n_ok, message=f"reference scan does not fit the declared "
                                                                   f"sphere: {e}")
        # In the published sign from here on: residual = actual − predicted deviation (measured − nominal).
        actual = published_deviation(target)
        pred = published_deviation(pred)
        nrm = used.normals(used.project(p[ok]))
        a_n = np.einsum("ij,ij->i", actual, nrm)
        med = float(np.median(np.abs(a_n)))
        if med > self.spec.max_mismatch_mm:
            c = self.spec.center_mm
            where = "fitted" if self.spec.fit_center else f"declared at ({c[0]:g}, {c[1]:g}, {c[2]:g}) mm"
            return ReferenceResult("MISMATCH", n_mon, n_ok, actual_mean_abs_mm=float(np.mean(np.abs(a_n))),
                                   message=f"reference scan does not show the sphere of radius "
                                           f"{self.spec.radius_mm:g} mm {where}: median |normal error| "
                                           f"{med:.3f} mm > {self.spec.max_mismatch_mm:g} mm")
        u = None if U_mm is None else np.asarray(U_mm, dtype=np.float64)[ok]
        if u is not None and not np.isfinite(u).any():
            u = None
        r_n = np.einsum("ij,ij->i", actual - pred[ok], nrm)
        # Spurious returns the outlier filter left (0.2-1.5 mm on a µm residual) would make the RMS jump on a stable
        # scanner: points beyond TRIM_SIGMA robust standard deviations of the residual are left out (and counted).
        med = float(np.median(r_n))
        sig = 1.4826 * float(np.median(np.abs(r_n - med)))
        keep = np.abs(r_n - med) <= TRIM_SIGMA * max(sig, 1e-6)
        state = self.monitor.update(actual[keep], pred[ok][keep], None if u is None else u[keep], nrm[keep])
        # the reported residual statistics are the monitored ones (drift.scan_statistics)
        st = state.stats
        res = ReferenceResult(state.state, self.monitor.n, int(keep.sum()),
                              actual_mean_abs_mm=float(np.mean(np.abs(a_n[keep]))),
                              residual_mean_mm=st["residual_mean"], residual_rms_mm=float(np.exp(st["residual_rms"])),
                              coverage=float(st.get("coverage", float("nan"))), drift=state,
                              trimmed=int((~keep).sum()))
        if state.state == "WARN" and candidates is not None:
            cands = candidates() if callable(candidates) else candidates
            idx = np.flatnonzero(ok)[keep]
            res.screening = screen_candidates(r_n[keep], {k: np.asarray(v)[idx] for k, v in cands.items()})
            named = [(abs(v["rho"]), k) for k, v in res.screening.items()
                     if v["p"] < CANDIDATE_ALPHA and abs(v["rho"]) >= CANDIDATE_MIN_RHO]
            if named:
                _, best = max(named)
                res.candidate = best
                res.candidate_rho = res.screening[best]["rho"]
                res.candidate_p = res.screening[best]["p"]
        res.message = _message(res)
        return res


def _message(res: ReferenceResult) -> str:
    base = res.drift.message if res.drift is not None else res.state.lower()
    if res.state != "WARN":
        tail = f" ({res.points} points, {res.trimmed} spurious left out)"
    elif res.candidate:
        tail = (f"; candidate effect: {res.candidate} (Spearman {res.candidate_rho:+.2f}, Holm p "
                f"{res.candidate_p:.1e})")
    else:
        tail = "; no candidate variable stands out"
    return (f"reference {base}: residual mean {res.residual_mean_mm * 1e3:+.1f} µm, RMS "
            f"{res.residual_rms_mm * 1e3:.1f} µm{tail}")


def live_candidates(prepared: Any) -> dict[str, np.ndarray]:
    """The screening's candidates from a pre-processed scan (``preprocess.Prepared``): its per-point fields (t, u,
    intensity, line, ...), incidence and view angles (deg), stand-off (mm) and the scan-frame position x, y, z (mm)."""
    out: dict[str, np.ndarray] = {}
    for k, v in (prepared.fields or {}).items():
        out[str(k)] = np.asarray(v, dtype=np.float64)
    n = np.asarray(prepared.normals, dtype=np.float64)
    g = prepared.geometry
    for name, d in (("incidence_deg", g.L), ("view_deg", g.V)):
        c = np.einsum("ij,ij->i", n, np.asarray(d, dtype=np.float64))
        out[name] = np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))
    out["standoff"] = np.asarray(g.standoff, dtype=np.float64)
    p = np.asarray(prepared.points, dtype=np.float64)
    for j, a in enumerate("xyz"):
        out[a] = p[:, j]
    return out
