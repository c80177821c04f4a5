"""Verify a rescan recommendation by re-simulation (ROS-free): what the recommended set-up *actually* gives.

Given the ground truth of a simulated judged scan (artifact, settings, head pose, seed, scanner, effects), a region
of the artifact and a set-up (settings + head pose at scan start), the virtual scanner re-scans the artifact at that
set-up with several seeds (never the judged scan's own seed) and reports, over the re-simulated points whose
*nominal* point (their projection on the artifact) lies in the region:

- the actual error e = nominal − measured (noise included): p95 and mean of |e| (norm over x, y, z), mm, averaged
  over the seeds, with the spread of the p95 over the seeds (the noise of re-simulation itself);
- its systematic part (the simulator's ``expected_error``) and its random part (e − expected_error): p95 of the norm;
- the coverage of the region: the fraction of the region's reference points with a re-simulated point within
  ``tol_mm`` (reference points: the given surface points, or for a ball region the points the judged set-up itself
  returns there, noise-free).

Only the rows and columns of the scan grid that can see the region are simulated (``simulate_scan(window=...)``):
the same rays as a full scan, a few percent of them, so re-simulating the 27 settings × 25 orientations of a search
takes tens of seconds rather than an hour. When the region lies behind the start of a rotated scan (head +Y), the
scan starts earlier along the same line (the start pose is moved back along head −Y; the orientation is kept).

``verify`` runs the whole check of one recommendation: before (the current set-up), after (the recommended one),
optionally every candidate of the search and the actual best among them, next to the predicted figures.

The actual best is found in two steps, because the smallest of hundreds of noisy p95 estimates is biased low (the
winner's curse: with one re-simulation per candidate the "best" is mostly the luckiest draw, 1-2 µm below what that
set-up gives on average, comparable to the differences being judged). Every candidate is re-simulated with
*selection* seeds; the ``finalists`` lowest are re-simulated again with the *evaluation* seeds (those of before and
after, distinct from the selection seeds), and the best is the lowest of those and the recommendation. Before,
after and best are then measured on the same draws, and after / best ≥ 1 by construction.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ..scan.artifacts import Artifact
from ..scan.geometry import HeadPose
from ..scan.scan import Scan
from ..scan.scanner import ScannerModel, ScanSettings

__all__ = ["ActualError", "GroundTruth", "Region", "Verification", "effect_ablation", "resimulate", "resimulate_many",
           "verify"]

MARGIN_MM = 1.0  # window margin around the region (rays that see the region's rim)


@dataclass
class GroundTruth:
    """What the simulator needs to scan the judged artifact again (scan frame, mm)."""

    artifact: Artifact
    settings: ScanSettings
    pose: HeadPose
    seed: int
    scanner: ScannerModel
    effects: dict[str, Any] | None = None
    extent_mm: float | None = None

    @classmethod
    def from_scan(cls, scan: Scan, scanner: ScannerModel | None = None,
                  effects: dict[str, Any] | None = None) -> GroundTruth:
        """From a simulated scan (its artifact, settings, start pose and ``meta['seed']``)."""
        if scan.artifact is None:
            raise ValueError("the scan has no nominal artifact: it cannot be re-simulated")
        return cls(scan.artifact, scan.settings, scan.pose, int(scan.meta.get("seed", 0)),
                   scanner if scanner is not None else ScannerModel.load(), effects)


@dataclass
class Region:
    """A region of the artifact: a ball (``centre``, ``radius_mm``) or surface points (``points``, within
    ``tol_mm`` of one of them). Membership is tested on nominal points (projections on the artifact)."""

    centre: np.ndarray | None = None
    radius_mm: float | None = None
    points: np.ndarray | None = None
    tol_mm: float = 0.5
    _tree: Any = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.points is not None:
            self.points = np.asarray(self.points, dtype=np.float64).reshape(-1, 3)
            if len(self.points) == 0:
                raise ValueError("a region needs at least one point")
            self._tree = cKDTree(self.points)
        elif self.centre is None or self.radius_mm is None or not self.radius_mm > 0:
            raise ValueError("a region is a ball (centre, radius_mm > 0) or a set of surface points")
        else:
            self.centre = np.asarray(self.centre, dtype=np.float64).reshape(3)

    def contains(self, nominal: np.ndarray) -> np.ndarray:
        """(N,) bool: the nominal points that lie in the region."""
        nominal = np.asarray(nominal, dtype=np.float64)
        if self._tree is not None:
            d, _ = self._tree.query(nominal, distance_upper_bound=self.tol_mm)
            return np.isfinite(d)
        return np.linalg.norm(nominal - self.centre, axis=1) <= self.radius_mm

    def box(self) -> np.ndarray:
        """(8, 3) corners of an axis-aligned box holding the region, with a margin (scan frame, mm)."""
        if self._tree is not None and self.points is not None:
            lo, hi = self.points.min(axis=0) - self.tol_mm, self.points.max(axis=0) + self.tol_mm
        else:
            assert self.centre is not None and self.radius_mm is not None  # a ball (checked at construction)
            lo, hi = self.centre - self.radius_mm, self.centre + self.radius_mm
        lo, hi = lo - MARGIN_MM, hi + MARGIN_MM
        return np.array([[a[0], b[1], c[2]] for a in (lo, hi) for b in (lo, hi) for c in (lo, hi)])


@dataclass
class ActualError:
    """Re-simulated error of one set-up in the region (mm; norms over x, y, z; means over the seeds)."""

    settings: ScanSettings
    pose: HeadPose
    p95_mm: float                 # p95 of |e|, e = nominal − measured, noise included
    p95_spread_mm: float          # std of that p95 over the seeds (re-simulation noise); 0 with one seed
    mean_mm: float
    sys_p95_mm: float             # p95 of |expected_error| (systematic part)
    rand_p95_mm: float            # p95 of |e − expected_error| (random part)
    coverage: float               # fraction of the region's reference points re-scanned (within tol)
    n_points: float               # region points per re-simulation (mean over seeds)
    n_seeds: int
    predicted_p95_mm: float | None = None
    rotation: np.ndarray | None = None  # head-frame rotation relative to the current pose, when known


@dataclass
class Verification:
    """Predicted versus re-simulated actual error: before, after, and (optionally) all candidates."""

    before: ActualError
    after: ActualError
    candidates: list[ActualError]   # every candidate re-simulated (empty when not asked)
    best: ActualError | None        # the actual best candidate (lowest actual p95), None without candidates

    @property
    def after_over_best(self) -> float:
        """Actual p95 after / best actual p95 among the candidates (1.0 = the recommendation is the best)."""
        return self.after.p95_mm / self.best.p95_mm if self.best is not None else float("nan")

    @property
    def after_percentile(self) -> float:
        """Share of candidates whose actual p95 is lower than the recommendation's (0 = best, 1 = worst)."""
        if not self.candidates:
            return float("nan")
        a = np.array([c.p95_mm for c in self.candidates])
        return float(np.mean(a < self.after.p95_mm - 1e-12))

    def rank_correlation(self) -> float:
        """Spearman correlation between the predicted and the actual p95 over the candidates (NaN if fewer than 3
        candidates carry a prediction)."""
        from scipy.stats import spearmanr

        pairs = [(c.predicted_p95_mm, c.p95_mm) for c in self.candidates if c.predicted_p95_mm is not None]
        if len(pairs) < 3:
            return float("nan")
        p, a = np.array(pairs).T
        return float(spearmanr(p, a).statistic)


def _window(truth: GroundTruth, region: Region, settings: ScanSettings,
            pose: HeadPose) -> tuple[HeadPose, tuple[float, float, float, float]]:
    """Start pose and (s_lo, s_hi, u_lo, u_hi) window of the rays that can see the region's box."""
    ch = pose.to_head(region.box())
    s_lo = float(ch[:, 1].min())
    if s_lo < 0:  # the region lies behind the scan start: start earlier along the same line
        pose = HeadPose(pose.position + (s_lo - MARGIN_MM) * pose.rotation[:, 1], pose.rotation)
        ch = pose.to_head(region.box())
        s_lo = float(ch[:, 1].min())
    below = ch[:, 2] < 0
    r_ref = truth.scanner.standoff_mm
    if below.all():
        u = ch[:, 0] * r_ref / -ch[:, 2]
        u_lo, u_hi = float(u.min()), float(u.max())
    else:  # the box reaches the head plane: keep the whole fan
        u_lo, u_hi = -np.inf, np.inf
    return pose, (s_lo, float(ch[:, 1].max()), u_lo, u_hi)


def resim_seeds(truth: GroundTruth, n: int) -> list[int]:
    """``n`` seeds derived from the judged scan's seed, distinct from it (independent streams)."""
    ss = np.random.SeedSequence([int(truth.seed), 15])
    seeds = [int(x) for x in ss.generate_state(n + 1)]
    return [s for s in seeds if s != truth.seed][:n]


def _reference_points(truth: GroundTruth, region: Region) -> np.ndarray:
    """The region's reference surface points: the given ones, or the noise-free nominal points the judged set-up
    returns in the ball."""
    if region.points is not None:
        return region.points
    from ..sim import simulate_scan

    pose, win = _window(truth, region, truth.settings, truth.pose)
    scan = simulate_scan(truth.artifact, truth.settings, scanner=truth.scanner, pose=pose, effects=truth.effects,
                         seed=truth.seed, window=win, **_extent(truth))
    pts = scan.points.reshape(-1, 3)
    ok = np.isfinite(pts).all(axis=1)
    nominal = truth.artifact.project(pts[ok])
    return nominal[region.contains(nominal)]


def _extent(truth: GroundTruth) -> dict[str, Any]:
    return {} if truth.extent_mm is None else {"extent_mm": truth.extent_mm}


def resimulate(truth: GroundTruth, region: Region, settings: ScanSettings, pose: HeadPose, *, n_seeds: int = 3,
               seeds: Sequence[int] | None = None, reference: np.ndarray | None = None, cov_tol_mm: float | None = None,
               predicted_p95_mm: float | None = None) -> ActualError:
    """Re-simulate the artifact at ``settings`` from ``pose`` (head pose at scan start, scan frame) and measure the
    actual error in ``region`` (see the module docstring).

    Args:
        seeds: the re-simulation seeds; None → ``n_seeds`` seeds derived from (never equal to) the judged seed.
        reference: the region's reference points for the coverage (computed when None; pass it to share it).
        cov_tol_mm: a reference point is covered when a re-simulated nominal point lies within this distance;
            None → 1.5 × the grid's nominal spacing, max(1/lateral, 1/direction density).
    Raises:
        ValueError: the set-up sees nothing of the region's box (out of the fan, or behind the head).
    """
    from ..sim import simulate_scan

    seeds = list(seeds) if seeds is not None else resim_seeds(truth, n_seeds)
    ref = _reference_points(truth, region) if reference is None else reference
    tol = cov_tol_mm if cov_tol_mm is not None else 1.5 / min(settings.lateral_density, settings.direction_density)
    start, win = _window(truth, region, settings, pose)
    p95: list[float] = []
    mean: list[float] = []
    sys95: list[float] = []
    rand95: list[float] = []
    cov: list[float] = []
    npts: list[int] = []
    for sd in seeds:
        try:
            scan = simulate_scan(truth.artifact, settings, scanner=truth.scanner, pose=start, effects=truth.effects,
                                 seed=sd, window=win, **_extent(truth))
        except ValueError:  # nothing of the region is in view from this pose
            scan = None
        if scan is None:
            for lst in (p95, mean, sys95, rand95):
                lst.append(np.inf)
            cov.append(0.0)
            npts.append(0)
            continue
        pts = scan.points.reshape(-1, 3)
        ok = np.isfinite(pts).all(axis=1)
        meas = pts[ok]
        assert scan.expected_error is not None  # simulated scans carry it
        exp = scan.expected_error.reshape(-1, 3)[ok]
        nominal = truth.artifact.project(meas)
        inr = region.contains(nominal)
        e = (nominal - meas)[inr]
        npts.append(int(inr.sum()))
        if len(e) == 0:
            for lst in (p95, mean, sys95, rand95):
                lst.append(np.inf)
            cov.append(0.0)
            continue
        en = np.linalg.norm(e, axis=1)
        p95.append(float(np.percentile(en, 95)))
        mean.append(float(en.mean()))
        sys95.append(float(np.percentile(np.linalg.norm(exp[inr], axis=1), 95)))
        rand95.append(float(np.percentile(np.linalg.norm(e - exp[inr], axis=1), 95)))
        if len(ref):
            d, _ = cKDTree(nominal[inr]).query(ref, distance_upper_bound=tol)
            cov.append(float(np.isfinite(d).mean()))
        else:
            cov.append(0.0)
    p = np.asarray(p95)
    spread = float(p.std(ddof=1)) if len(p) > 1 and np.isfinite(p).all() else 0.0
    return ActualError(settings, pose, float(p.mean()), spread, float(np.mean(mean)), float(np.mean(sys95)),
                       float(np.mean(rand95)), float(np.mean(cov)), float(np.mean(npts)), len(seeds),
                       predicted_p95_mm)


def effect_ablation(truth: GroundTruth, region: Region, settings: ScanSettings, pose: HeadPose, *, n_seeds: int = 2,
                    seeds: Sequence[int] | None = None) -> dict[str, float]:
    """Which of the simulator's effects make a set-up's systematic error in ``region``: its systematic p95
    (``ActualError.sys_p95_mm``, mm) with every effect of the ground truth (key ``"all"``), then with each enabled
    effect switched off in turn (key: the effect's name), on the same seeds. Effects add vectors, so switching one
    off can also *raise* the p95 (it cancelled another one). To trace a mispredicted set-up to the effect the model
    misses: the effect whose removal brings the actual figure to the predicted one."""
    from ..sim.effects import resolve_effects

    seeds = list(seeds) if seeds is not None else resim_seeds(truth, n_seeds)
    ref = _reference_points(truth, region)  # once, as resimulate_many does (only the coverage reads it)
    out = {"all": resimulate(truth, region, settings, pose, seeds=seeds, reference=ref).sys_p95_mm}
    for fx in resolve_effects(truth.scanner.effects, truth.effects):
        off = replace(truth, effects={**(truth.effects or {}), fx.name: False})
        out[fx.name] = resimulate(off, region, settings, pose, seeds=seeds, reference=ref).sys_p95_mm
    return out


def resimulate_many(truth: GroundTruth, region: Region, setups: Sequence[tuple[ScanSettings, HeadPose]], *,
                    n_seeds: int = 2, seeds: Sequence[int] | None = None, reference: np.ndarray | None = None,
                    predicted: Sequence[float | None] | None = None,
                    rotations: Sequence[np.ndarray | None] | None = None) -> list[ActualError]:
    """``resimulate`` for each (settings, start pose) of ``setups`` with the same seeds (``seeds``, else ``n_seeds``
    derived from the judged seed) and reference points (``reference``, else computed once here)."""
    seeds = list(seeds) if seeds is not None else resim_seeds(truth, n_seeds)
    ref = _reference_points(truth, region) if reference is None else reference
    out = []
    for k, (s, pose) in enumerate(setups):
        a = resimulate(truth, region, s, pose, seeds=seeds, reference=ref,
                       predicted_p95_mm=None if predicted is None else predicted[k])
        a.rotation = None if rotations is None else rotations[k]
        out.append(a)
    return out


def _predicted(c: Any) -> float | None:
    """A candidate's predicted p95 of the actual |error|: its ``predicted_p95_mm`` (distribution), else its score."""
    v = getattr(c, "predicted_p95_mm", None)
    return v if v is not None else getattr(c, "score_mm", None)


def verify(truth: GroundTruth, region: Region, rec: Any, *, n_seeds: int = 3, all_candidates: bool = False,
           candidate_seeds: int = 2, finalists: int = 5) -> Verification:
    """Re-simulate the current set-up and the recommendation ``rec`` (a ``recommend.Recommendation``: its
    ``before`` and ``best`` candidates carry settings, start pose and predicted p95) in ``region`` with ``n_seeds``
    evaluation seeds; with ``all_candidates`` also every ranked candidate (``candidate_seeds`` selection seeds
    each, distinct from the evaluation seeds) and the actual best: the lowest, on the evaluation seeds, of the
    ``finalists`` candidates lowest on the selection seeds and the recommendation (module docstring)."""
    if finalists < 1:
        raise ValueError(f"finalists must be >= 1, got {finalists}")
    seeds = resim_seeds(truth, n_seeds + (candidate_seeds if all_candidates else 0))
    eval_seeds, sel_seeds = seeds[:n_seeds], seeds[n_seeds:]
    ref = _reference_points(truth, region)

    def one(c: Any) -> ActualError:
        a = resimulate(truth, region, c.settings, c.pose, seeds=eval_seeds, reference=ref,
                       predicted_p95_mm=_predicted(c))
        a.rotation = getattr(c, "rotation", None)
        return a

    before, after = one(rec.before), one(rec.best)
    cands: list[ActualError] = []
    best = None
    if all_candidates:
        cands = resimulate_many(truth, region, [(c.settings, c.pose) for c in rec.ranked], seeds=sel_seeds,
                                reference=ref, predicted=[_predicted(c) for c in rec.ranked],
                                rotations=[c.rotation for c in rec.ranked])
        order = np.argsort([a.p95_mm for a in cands], kind="stable")[:finalists]
        # the recommendation is measured already (``after``), when it is one of the finalists
        final = [after] + [one(rec.ranked[k]) for k in order if not _same_setup(rec.ranked[k], rec.best)]
        best = min(final, key=lambda a: a.p95_mm)
    return Verification(before, after, cands, best)


def _same_setup(a: Any, b: Any) -> bool:
    """The same settings and start pose (the recommendation is one of the ranked candidates)."""
    return bool(a.settings == b.settings and np.allclose(a.pose.position, b.pose.position)
                and np.allclose(a.pose.rotation, b.pose.rotation))
