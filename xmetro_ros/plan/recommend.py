"""Rescan recommendation (ROS-free): which settings and head orientation minimise the predicted error in a region.

Search (exhaustive grid, deterministic):
- the region's processed points are subsampled to at most ``max_points`` (evenly spaced rows, deterministic);
- orientations: tilts about head X and head Y in ``linspace(-max_tilt, max_tilt, tilt_steps)`` and turns about head
  Z in ``linspace(-max_turn, max_turn, turn_steps)`` (defaults 3 × 3 × 3 = 27 orientations, identity included),
  each applied to the current head pose about the region centroid (``HeadPose.rotated(r, pivot=centroid)``);
- settings: the candidates given, or the scanner's 27 study configurations.
For each orientation the geometry-dependent features are recomputed once (``FeatureContext.with_pose``) and only the
settings-dependent columns per settings; all candidates of one orientation go into one batched predict call.
A point is *covered* when lit and seen at non-grazing angles (acos(N·L) and acos(N·V) under the grazing
thresholds). Orientations covering less than ``min(min_coverage, current coverage)`` of the region are discarded
before any prediction.

Ranking by the total predicted error a user will see (systematic and random parts together): per covered point
``t = |d| + |U|`` where ``d`` (3,) is the predicted systematic error and ``U`` (3,) the predicted expanded (95 %)
uncertainty per axis, both mm, norms over x, y, z; a candidate's score is the p95 of ``t`` over its covered points
(ties: the mean of |d|). ``|e| = |d + r| <= |d| + |r|`` and laser triangulation noise lies mostly along one
direction (the ray), so ``|U|`` bounds ``|r|`` at about 95 % per point: the score is a (slightly conservative)
prediction of the p95 of the actual |error| in the region. U comes from ``uncertainty(model_set, X) -> (M, 3)``;
by default from the model set's ``predict_with_uncertainty(X) -> (d, U)`` when it has one; otherwise U = 0, the score
is the p95 of |d| (the ranking of earlier versions) and the note says the ranking ignores noise.

The random part at each candidate's exposure, calibrated: U is multiplied by ``u_scale(exposure)``
(``exposure_u_scale``, default :data:`EXPOSURE_U_SCALE`, linear in log exposure between its points, clipped at its
ends) before it enters the score and the predicted p95. The table is the median over every candidate of the nine
*validation* regions (``xmetro verify-recommend --calibrate``, seeds 8000+; never the test regions) of
the re-simulated random-part p95 over the p95 of |U|, relative to 0.5 ms: the shipped pose model's U, right on whole
looking-down scans, under-states the random part of the searched orientations by ~7 % at 2 ms and ~39 % at 0.1 ms
relative to 0.5 ms.

Keeping the current set-up ("keep" is a candidate like any other): the best-ranked candidate is recommended only
when its predicted gain over the current set-up (evaluated like every candidate) exceeds the gain's uncertainty.
The gain is taken on the figure that is compared with the actual p95 (``reported_p95_mm``: the predicted p95 of
|d + r| when the model gives U, else the score); its uncertainty is ``sqrt(u_before² + u_top²)``, each figure's
``u = sqrt(ci² + (k · p)²)``: ``ci`` the half-width of the distribution-free 95 % confidence interval of a p95 from
the candidate's covered points (binomial order statistics of the per-point |d| + |U|: the finite region, the spread
of the per-point errors and U), ``k · p`` the model's own error in predicting a region's p95 ``p`` (shared by all its
points, unseen by ``ci``). ``k`` (``prediction_rel_unc``, default :data:`PREDICTION_REL_UNC`) is the 5 % quantile
of the over-predicted gain, (predicted − re-simulated gain) / sqrt(p_before² + p_candidate²), over the 20
best-ranked candidates of each validation region (so the optimism of picking the lowest of hundreds of predictions
is in it). Otherwise ``best`` is the current set-up, ``kept_current`` is
True and the note says "keep the current set-up" with the gain and its uncertainty (the service's ``message``).

Domain: ``in_domain(X) -> (M,) bool`` (default: the model set's ``in_domain`` when it has one, else not
``out_of_domain``, else no check). A candidate whose share of covered points outside the domain exceeds
``max_out_of_domain`` is discarded (its predictions are extrapolations); the note says how many were.

A time budget (``max_seconds``) stops the search after the orientation in progress; the current orientation is
always evaluated first, and the note says when the search was cut short.

Limits (honest): no occlusion by other parts of the workpiece unless its CAD is given (``occluder``), no
reachability of the pose; the normals are those
of the current scan; ``EXPOSURE_U_SCALE`` and ``PREDICTION_REL_UNC`` are the shipped pose model's. A model set of
one's own is calibrated with ``xmetro verify-recommend --calibrate --pose-model DIR --write-card DIR``: the figures go
into its card's ``recommend`` block, which the search then uses instead (:func:`recommend_calibration`; the note
says which calibration was used).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..scan.geometry import HeadPose, matrix_to_quat, orientation_grid
from ..scan.scanner import ScannerModel, ScanSettings

__all__ = [
    "EXPOSURE_U_SCALE",
    "FROM_MODEL",
    "PREDICTION_REL_UNC",
    "Candidate",
    "RecommendCalibration",
    "RecommendCancelled",
    "RecommendProgress",
    "Recommendation",
    "coverage_mask",
    "gain_and_uncertainty",
    "recommend",
    "recommend_calibration",
    "u_scale",
]


@dataclass
class Candidate:
    """One evaluated set-up: settings and head rotation, predicted figures over the covered points (mm), coverage.

    ``mean_mm`` / ``p95_mm``: mean and p95 of the predicted *systematic* |d|; ``total_p95_mm``: p95 of |d| + |U|
    (the ranking score, = ``p95_mm`` when U = 0); ``score_unc_mm``: half-width of the 95 % confidence interval of
    that p95 (order statistics); ``u_p95_mm``: p95 of |U|; ``out_of_domain``: share of covered points outside the
    model's domain."""

    settings: ScanSettings
    rotation: np.ndarray          # 3x3, in the head frame, relative to the current head pose
    pose: HeadPose                # the resulting head pose (scan frame, mm)
    mean_mm: float
    p95_mm: float
    coverage: float
    total_p95_mm: float | None = None
    score_unc_mm: float = 0.0
    u_p95_mm: float = 0.0
    out_of_domain: float = 0.0
    predicted_p95_mm: float | None = None  # p95 of |d + r|, r ~ N(0, (U / 1.96)²) per axis: vs the actual p95

    @property
    def quaternion(self) -> np.ndarray:
        """The rotation as a quaternion (x, y, z, w)."""
        return matrix_to_quat(self.rotation)

    @property
    def reported_p95_mm(self) -> float:
        """The p95 |error| a user is told to expect (mm): the predicted total (systematic + random, from the
        predicted distribution) when the model gives U, else the systematic p95 (``p95_mm``)."""
        return self.predicted_p95_mm if self.predicted_p95_mm is not None else self.p95_mm

    @property
    def score_mm(self) -> float:
        """The ranking score: predicted p95 of the total |error| (systematic + random), mm."""
        return self.p95_mm if self.total_p95_mm is None else self.total_p95_mm


@dataclass
class RecommendProgress:
    """Progress of a :func:`recommend` search (after ``evaluated`` orientations)."""

    evaluated: int                # orientations evaluated so far
    total: int                    # orientations in the grid
    kept: int                     # of which kept (coverage high enough)
    n_settings: int               # settings tried per kept orientation
    elapsed_s: float
    best_p95_mm: float            # best p95 |error| so far (inf: none yet)


class RecommendCancelled(Exception):
    """:func:`recommend` stopped because its ``cancelled`` callback returned true."""


@dataclass
class Recommendation:
    """The search result: the best candidate, the current set-up (``before``), the ranking and a note."""

    best: Candidate
    before: Candidate
    ranked: list[Candidate]       # best first, every kept candidate
    n_points: int                 # region points used (after the subsample)
    n_region: int                 # region points before the subsample
    n_orientations: int
    n_orientations_kept: int
    n_settings: int
    note: str
    n_orientations_evaluated: int = 0
    kept_current: bool = False    # True: no candidate's predicted gain exceeds its uncertainty; best = current
    uses_uncertainty: bool = False  # False: U = 0, the ranking ignores noise
    n_out_of_domain: int = 0      # candidates discarded as outside the model's domain
    top: Candidate | None = None  # the best-ranked candidate (= best unless kept_current)
    gain: tuple[float, float] | None = None  # the keep rule's predicted gain of ``top`` and its uncertainty (mm)


def coverage_mask(ctx: Any, grazing_incidence_deg: float, grazing_view_deg: float, occluder: Any = None
                  ) -> np.ndarray:
    """Points lit and seen at non-grazing angles under the context's geometry; with an ``occluder`` (an artifact
    with ``project`` and ``intersect``, e.g. the part's CAD ``mesh.MeshArtifact`` in the scan frame) also neither
    in its laser shadow nor hidden from the camera by it (rays from the point's projection on it along L and V)."""
    n = np.asarray(ctx.normals, dtype=np.float64)
    L, V = np.asarray(ctx.L, dtype=np.float64), np.asarray(ctx.V, dtype=np.float64)
    cos_i = np.einsum("ij,ij->i", n, L)
    cos_v = np.einsum("ij,ij->i", n, V)
    m = (cos_i > np.cos(np.radians(grazing_incidence_deg))) & (cos_v > np.cos(np.radians(grazing_view_deg)))
    if occluder is not None and m.any():
        i = np.flatnonzero(m)
        p = occluder.project(np.asarray(ctx.points, dtype=np.float64)[i])
        m[i] = ~np.isfinite(occluder.intersect(p, L[i])) & ~np.isfinite(occluder.intersect(p, V[i]))
    return m


def p95_interval_halfwidth(values: np.ndarray) -> np.ndarray:
    """Half-width (…,) of the distribution-free 95 % confidence interval of the 95th percentile of ``values``
    (…, n), from binomial order statistics: ranks n·0.95 ∓ 1.96·sqrt(n·0.95·0.05). inf when n = 0."""
    n = values.shape[-1]
    if n == 0:
        return np.full(values.shape[:-1], np.inf)
    half = 1.96 * np.sqrt(n * 0.95 * 0.05)
    lo = int(np.clip(np.floor(n * 0.95 - half) - 1, 0, n - 1))
    hi = int(np.clip(np.ceil(n * 0.95 + half) - 1, 0, n - 1))
    v = np.sort(values, axis=-1)
    return (v[..., hi] - v[..., lo]) / 2.0


# Calibrated on the validation regions (seeds 8000+) with the shipped pose model: see the module docstring and
# ``xmetro verify-recommend --calibrate``. A model set whose card has a ``recommend`` block (``xmetro
# verify-recommend --calibrate --write-card DIR``) uses its own figures instead (:func:`recommend_calibration`).
EXPOSURE_U_SCALE: dict[float, float] = {0.1: 1.39, 0.5: 1.0, 2.0: 1.07}  # exposure (ms) → factor on U
PREDICTION_REL_UNC = 0.10  # the model's error in predicting a candidate's p95 (gain), relative to that p95
FROM_MODEL = "model"  # recommend()'s default for both: the searched model set's own calibration, else the above


@dataclass(frozen=True)
class RecommendCalibration:
    """The recommender's calibration of one model set: the factor on U per exposure (ms → factor), the relative
    uncertainty of a predicted p95 (the keep-current rule), and where they come from."""

    exposure_u_scale: dict[float, float]
    prediction_rel_unc: float
    source: str


def recommend_calibration(model_set: Any) -> RecommendCalibration:
    """The calibration in ``model_set``'s card (its ``recommend`` block, written by ``xmetro verify-recommend
    --calibrate --write-card``), else the shipped pose model's (:data:`EXPOSURE_U_SCALE`,
    :data:`PREDICTION_REL_UNC`). Raises ValueError for a malformed block (a card is a user's file)."""
    block = (getattr(model_set, "card", None) or {}).get("recommend")
    if not block:
        return RecommendCalibration(dict(EXPOSURE_U_SCALE), PREDICTION_REL_UNC, "the shipped pose model's")
    try:
        table = {float(e): float(f) for e, f in dict(block["exposure_u_scale"]).items()}
        k = float(block["prediction_rel_unc"])
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"the model card's 'recommend' block is malformed: {type(e).__name__}: {e}") from e
    if not (math.isfinite(k) and k >= 0) or not all(math.isfinite(e) and e > 0 and math.isfinite(f) and f > 0
                                                    for e, f in table.items()):
        raise ValueError("the model card's 'recommend' block needs prediction_rel_unc >= 0 and positive finite "
                         f"exposures and factors, got {block!r}")
    return RecommendCalibration(table, k, "the model card's")


def u_scale(exposure_ms: float, table: dict[float, float] | None) -> float:
    """The factor on U at ``exposure_ms`` from ``table`` (exposure ms → factor): linear in log exposure between its
    points, clipped at its ends; 1 without a table."""
    if not table:
        return 1.0
    e = np.array(sorted(table), dtype=np.float64)
    return float(np.interp(np.log(exposure_ms), np.log(e), [table[k] for k in sorted(table)]))


RANK_BY = ("score", "predicted")  # ranking figures (recommend's rank_by)
N_DRAWS = 4  # draws per point of the predicted error distribution (the predicted p95 of the actual error)


def _scores(pred: np.ndarray, unc: np.ndarray | None, covered: np.ndarray, z: np.ndarray | None = None
            ) -> tuple[np.ndarray, ...]:
    """Per candidate (S,): mean |d|, p95 |d|, p95 (|d| + |U|), its CI half-width, p95 |U|, and the p95 of |d + r|
    with r ~ N(0, (U / 1.96)²) per axis (``z``: (N_DRAWS, m, 3) standard normal draws, the same for every
    candidate so that they compare on common random numbers) over covered points."""
    # a slice, not a copy, when every point is covered (the usual case)
    sel: slice | np.ndarray = slice(None) if covered.all() else covered
    pc = pred[..., sel, :]
    d = np.sqrt(np.einsum("...ij,...ij->...i", pc, pc))
    empty = np.full(pred.shape[:-2], np.inf)
    if not d.shape[-1]:
        return empty, empty, empty, empty, empty, empty
    mean, p95 = d.mean(axis=-1), np.percentile(d, 95, axis=-1)
    if unc is None:
        return mean, p95, p95, p95_interval_halfwidth(d), np.zeros(pred.shape[:-2]), p95
    uc = unc[..., sel, :]
    u = np.sqrt(np.einsum("...ij,...ij->...i", uc, uc))
    t = d + u
    if z is None:
        z = np.random.default_rng(0).standard_normal((N_DRAWS, *uc.shape[-2:]), dtype=np.float32)
    else:
        z = z[:, sel]
    # (S, D, m, 3): the predicted error of every point in D draws (float32: a p95 needs no more)
    e = pc.astype(np.float32)[..., None, :, :] + (uc * (1 / 1.96)).astype(np.float32)[..., None, :, :] * z
    en = np.sqrt(np.einsum("...ij,...ij->...i", e, e)).reshape(*pred.shape[:-2], -1)
    return (mean, p95, np.percentile(t, 95, axis=-1), p95_interval_halfwidth(t), np.percentile(u, 95, axis=-1),
            np.percentile(en, 95, axis=-1))


UncertaintyFn = Callable[[Any, np.ndarray], np.ndarray]


def _default_uncertainty(model_set: Any) -> UncertaintyFn | None:
    """U from the model set's ``predict_with_uncertainty(X)`` (an ``inference.UncertainPrediction`` or a (d, U)
    pair) when it has one and is calibrated, else None (U = 0)."""
    f = getattr(model_set, "predict_with_uncertainty", None)
    if not callable(f) or not getattr(model_set, "calibrated", True):
        return None

    def u(ms: Any, X: np.ndarray) -> np.ndarray:
        r = ms.predict_with_uncertainty(X)
        return np.asarray(r.U if hasattr(r, "U") else r[1], dtype=np.float64)

    return u


def _default_in_domain(model_set: Any) -> Callable[[np.ndarray], np.ndarray] | None:
    """The model set's own domain measure: ``in_domain(X)``, else not ``out_of_domain_mv(X)`` (the multivariate
    domain), else not ``out_of_domain(X)``, else None."""
    f = getattr(model_set, "in_domain", None)
    if callable(f):
        return lambda X: np.asarray(f(X), dtype=bool)
    mv = getattr(model_set, "out_of_domain_mv", None)
    if callable(mv):
        return lambda X: ~np.asarray(mv(X), dtype=bool)
    g = getattr(model_set, "out_of_domain", None)
    if callable(g):
        return lambda X: ~np.asarray(g(X), dtype=bool)
    return None


def gain_and_uncertainty(before: Candidate, top: Candidate, rel_unc: float = PREDICTION_REL_UNC
                         ) -> tuple[float, float]:
    """The predicted gain of ``top`` over ``before`` on the reported p95 (mm) and its uncertainty (mm):
    ``sqrt(ci_before² + ci_top² + rel_unc² · (p_before² + p_top²))`` (module docstring); an infinite gain when the
    current set-up covers none of the region's points."""
    pb, pt = before.reported_p95_mm, top.reported_p95_mm
    if not np.isfinite(pb):  # the current set-up covers none of the region: any covering candidate is a gain
        return math.inf, float(np.sqrt(top.score_unc_mm**2 + (rel_unc * pt)**2))
    return pb - pt, float(np.sqrt(before.score_unc_mm**2 + top.score_unc_mm**2 + rel_unc**2 * (pb**2 + pt**2)))


def recommend(model_set: Any, ctx: Any, rows: np.ndarray, before_features: np.ndarray, pose: HeadPose,
              scanner: ScannerModel, settings: ScanSettings, candidates: list[ScanSettings] | None = None, *,
              max_points: int = 2000, max_tilt: float = 0.2618, tilt_steps: int = 3, max_turn: float = 1.5708,
              turn_steps: int = 3, grazing_incidence_deg: float = 75.0, grazing_view_deg: float = 75.0,
              min_coverage: float = 0.95, batch_rows: int = 400_000,
              max_seconds: float | None = None, uncertainty: UncertaintyFn | None = None,
              in_domain: Callable[[np.ndarray], np.ndarray] | bool | None = None, max_out_of_domain: float = 0.05,
              keep_current: bool = True, rank_by: str = "score",
              exposure_u_scale: dict[float, float] | str | None = FROM_MODEL,
              prediction_rel_unc: float | str = FROM_MODEL,
              progress: Callable[[RecommendProgress], None] | None = None,
              cancelled: Callable[[], bool] | None = None, occluder: Any = None) -> Recommendation:
    """Search settings × orientations for the region ``rows`` of a judged scan (see the module docstring).

    Args:
        model_set: inference.ModelSet (feature_names, predict / predict_batch in mm; optionally
            predict_with_uncertainty, in_domain / out_of_domain). Several at once: ``ensemble_search.search``.
        ctx: FeatureContext of the judged scan's processed points.
        rows: region rows into ``ctx`` (non-empty).
        before_features: (M, F) the judged features of all rows (the "before" prediction uses them; the region
            subsample is predicted as its own cloud, like every candidate, so with a PointNet model "before" can
            differ slightly from the published deviations of the whole scan, but compares like with like).
        pose, scanner, settings: the current head pose (mm), scanner, settings.
        candidates: settings to try; None → ``scanner.study_configurations()``.
        max_seconds: time budget; the search stops (and says so in the note) once it is spent, after at least the
            current orientation (evaluated first).
        uncertainty: ``(model_set, X (M, F)) -> U (M, 3)`` mm, the expanded (95 %) uncertainty per axis of one
            cloud's predictions; None → the model set's ``predict_batch_with_uncertainty(Xq (Q, M, F)) -> (d, U)``
            (both (Q, M, 3), one call for all settings versions) if any, else its ``predict_with_uncertainty``
            (one call per version), else U = 0.
        in_domain: ``X (M, F) -> (M,) bool``; None → the model set's own measure if any; False → no check.
        max_out_of_domain: candidates with a larger share of covered points outside the domain are discarded.
        keep_current: recommend the current set-up unless the best predicted gain exceeds its uncertainty.
        exposure_u_scale: exposure (ms) → factor on U (:func:`u_scale`), the random part's calibrated size at each
            candidate's exposure; None or {} → U as the model gives it; ``"model"`` (default) → the model set's
            own calibration (:func:`recommend_calibration`).
        prediction_rel_unc: the model's relative error in predicting a candidate's p95 (the keep-current rule);
            ``"model"`` (default) → the model set's own calibration.
        rank_by: ``"score"`` (default): the p95 of |d| + |U| (``Candidate.score_mm``); ``"predicted"``: the p95 of
            the predicted distribution of |d + r| (``Candidate.predicted_p95_mm``; the score when the model gives
            no U). The keep-current rule compares that figure under either ranking.
        progress: called after each orientation with a :class:`RecommendProgress` (the ROS action's feedback).
        cancelled: polled before each orientation; true → :class:`RecommendCancelled` is raised.
        occluder: the part (an artifact in the scan frame, e.g. its CAD mesh): a point it shadows from the laser
            or hides from the camera under an orientation is not covered there (:func:`coverage_mask`).

    Raises:
        ValueError: empty region, or no orientation keeps the required coverage (or every candidate is outside
            the model's domain).
        RecommendCancelled: ``cancelled()`` became true.
    """
    from ..judge.features import REGISTRY, compute_features

    if rank_by not in RANK_BY:
        raise ValueError(f"rank_by must be one of {', '.join(RANK_BY)}, got {rank_by!r}")
    cal_source = ""
    if FROM_MODEL in (exposure_u_scale, prediction_rel_unc):
        cal = recommend_calibration(model_set)
        cal_source = cal.source
        exposure_u_scale = cal.exposure_u_scale if exposure_u_scale == FROM_MODEL else exposure_u_scale
        prediction_rel_unc = cal.prediction_rel_unc if prediction_rel_unc == FROM_MODEL else prediction_rel_unc
    if isinstance(exposure_u_scale, str) or isinstance(prediction_rel_unc, str):
        raise ValueError(f"exposure_u_scale and prediction_rel_unc take values or {FROM_MODEL!r}")

    def key(c: Candidate) -> tuple[float, float]:
        v = c.predicted_p95_mm if rank_by == "predicted" and c.predicted_p95_mm is not None else c.score_mm
        return (v, c.mean_mm)

    rows = np.asarray(rows, dtype=np.int64)
    rows = rows[np.isfinite(before_features[rows]).all(axis=1)]
    if len(rows) == 0:
        raise ValueError("the region holds no processed point")
    n_region = len(rows)
    if n_region > max_points:
        rows = rows[np.linspace(0, n_region - 1, max_points).round().astype(np.int64)]
    cands = list(candidates) if candidates else scanner.study_configurations()
    names = list(model_set.feature_names)
    sub = ctx.subset(rows)
    centroid = np.asarray(sub.points, dtype=np.float64).mean(axis=0)
    unc_fn = uncertainty if uncertainty is not None else _default_uncertainty(model_set)
    # Fast path: a model set predicting d and U of Q cloud versions in one call (no second pass per settings).
    batch_du = getattr(model_set, "predict_batch_with_uncertainty", None) if uncertainty is None else None
    batch_du = batch_du if callable(batch_du) else None
    dom_fn: Callable[[np.ndarray], np.ndarray] | None
    if in_domain is False or in_domain is True:
        dom_fn = None if in_domain is False else _default_in_domain(model_set)
    else:
        dom_fn = in_domain if in_domain is not None else _default_in_domain(model_set)

    def predict_unc(X: np.ndarray) -> np.ndarray | None:
        """(S, m, F) → U (S, m, 3), one cloud per settings version; None without an uncertainty source."""
        if unc_fn is None:
            return None
        return np.stack([np.asarray(unc_fn(model_set, X[k]), dtype=np.float64) for k in range(len(X))])

    def ood_share(X: np.ndarray, cov: np.ndarray) -> np.ndarray:
        """(S,) share of covered points outside the domain."""
        if dom_fn is None or not cov.any():
            return np.zeros(len(X))
        inside = np.asarray(dom_fn(X[:, cov].reshape(-1, X.shape[-1])), dtype=bool).reshape(len(X), -1)
        return 1.0 - inside.mean(axis=1)

    cov_before = coverage_mask(sub, grazing_incidence_deg, grazing_view_deg, occluder)
    Xb = np.asarray(before_features[rows], dtype=np.float32)[None]
    if batch_du is not None:
        d_b, u_b = batch_du(Xb)
        pred_before, unc_before = np.asarray(d_b, np.float64), np.asarray(u_b, np.float64)
    else:
        pred_before = np.asarray(model_set.predict(Xb[0]), dtype=np.float64)[None]
        unc_before = predict_unc(Xb)  # type: ignore[assignment]
    if unc_before is not None:
        unc_before = unc_before * u_scale(settings.exposure_ms, exposure_u_scale)
    scale = np.array([u_scale(c.exposure_ms, exposure_u_scale) for c in cands])[:, None, None]
    # common random numbers for the predicted error distribution: one deterministic draw set for all candidates
    z = np.random.default_rng(0).standard_normal((N_DRAWS, len(rows), 3), dtype=np.float32)
    mb, pb, tb, ub, u95b, eb = _scores(pred_before, unc_before, cov_before, z)
    before = Candidate(settings, np.eye(3), pose, float(mb[0]), float(pb[0]), float(cov_before.mean()),
                       float(tb[0]), float(ub[0]), float(u95b[0]), float(ood_share(Xb, cov_before)[0]), float(eb[0]))
    need = min(min_coverage, before.coverage) - 1e-12

    dep = [j for j, n in enumerate(names) if "settings" in tuple(REGISTRY.get(n).inputs)]
    dep_names = [names[j] for j in dep]
    orients = orientation_grid(max_tilt, tilt_steps, max_turn, turn_steps)
    # The current orientation first: it is always evaluated, whatever the time budget.
    orients.sort(key=lambda r: not np.allclose(r, np.eye(3)))
    t_start = time.monotonic()
    ranked: list[Candidate] = []
    n_kept = n_eval = n_ood = 0
    m = len(rows)
    best_p95 = math.inf
    for r in orients:
        if cancelled is not None and cancelled():
            raise RecommendCancelled(f"cancelled after {n_eval} of {len(orients)} orientations")
        if max_seconds is not None and n_eval and time.monotonic() - t_start > max_seconds:
            break
        if progress is not None and n_eval:
            progress(RecommendProgress(n_eval, len(orients), n_kept, len(cands), time.monotonic() - t_start,
                                       best_p95))
        n_eval += 1
        pose_o = pose.rotated(r, pivot=centroid)
        ctx_o = sub.with_pose(pose_o, scanner)
        cov = coverage_mask(ctx_o, grazing_incidence_deg, grazing_view_deg, occluder)
        if cov.mean() < need or not cov.any():
            continue
        n_kept += 1
        # (S, m, F): the S settings versions of the same region cloud, predicted together (predict_batch keeps
        # one PointNet set partition for all versions, as predict would for each).
        # Geometry features once per orientation; only the settings-dependent columns per settings.
        X = np.repeat(compute_features(names, ctx_o.with_settings(cands[0]), dtype=np.float32)[None], len(cands),
                      axis=0)
        for k in range(1 if dep else len(cands), len(cands)):
            X[k][:, dep] = compute_features(dep_names, ctx_o.with_settings(cands[k]), dtype=np.float32)
        ok = np.isfinite(X).all(axis=(0, 2))
        cov = cov & ok
        X[:, ~ok] = 0.0
        step = max(1, batch_rows // m)
        if batch_du is not None:
            du = [batch_du(X[i:i + step]) for i in range(0, len(X), step)]
            pred = np.concatenate([np.asarray(a, np.float64) for a, _ in du])
            unc = np.concatenate([np.asarray(b, np.float64) for _, b in du])
        else:
            pred = np.concatenate([np.asarray(model_set.predict_batch(X[i:i + step]), dtype=np.float64)
                                   for i in range(0, len(X), step)])
            unc = predict_unc(X)  # type: ignore[assignment]  # None: no source of U (the scores treat U as 0)
        if unc is not None:
            unc = unc * scale
        means, p95s, tots, uncs, u95s, e95s = _scores(pred, unc, cov, z)
        ood = ood_share(X, cov)
        for k, s in enumerate(cands):
            if ood[k] > max_out_of_domain:
                n_ood += 1
                continue
            ranked.append(Candidate(s, r, pose_o, float(means[k]), float(p95s[k]), float(cov.mean()),
                                    float(tots[k]), float(uncs[k]), float(u95s[k]), float(ood[k]), float(e95s[k])))
        if ranked:
            lead = min(ranked, key=key)
            best_p95 = lead.reported_p95_mm
    if not ranked:
        if n_ood:
            raise ValueError(f"all {n_ood} candidates keeping the coverage lie outside the model's domain "
                             f"(> {max_out_of_domain:.0%} of their points)")
        raise ValueError(f"no orientation keeps the coverage >= {need:.3f} of the region")
    ranked.sort(key=key)
    note = f"{len(orients)} orientations ({n_kept} kept) x {len(cands)} settings on {m} points"
    if n_eval < len(orients):
        note += (f"; time budget of {max_seconds:g} s spent: search stopped after {n_eval} of {len(orients)} "
                 "orientations")
    if n_region > m:
        note += f" (region of {n_region} points subsampled, evenly spaced)"
    uses_u = unc_fn is not None or batch_du is not None
    if not uses_u:
        note += "; ranked by the predicted systematic error only: the model gives no uncertainty, noise is ignored"
    else:
        note += ("; ranked by the p95 of |d| + |U| (systematic and random parts)" if rank_by == "score" else
                 "; ranked by the predicted p95 of |d + r| (systematic and random parts)")
    if dom_fn is None:
        note += "; no domain check"
    elif n_ood:
        note += (f"; {n_ood} candidates discarded: more than {max_out_of_domain:.0%} of their points outside the "
                 "model's domain")
    if uses_u and exposure_u_scale:
        note += "; U at each exposure scaled to the random part's calibrated size"
    if cal_source:
        note += f"; recommender calibration: {cal_source}"
    top = ranked[0]
    best, kept = top, False
    gain_pair: tuple[float, float] | None = None
    if keep_current:
        gain, gain_unc = gain_pair = gain_and_uncertainty(before, top, prediction_rel_unc)
        if not gain > gain_unc:
            # The current set-up, evaluated like the candidates when it is one of them (same cloud prediction).
            cur = [c for c in ranked if c.settings == settings and np.allclose(c.rotation, np.eye(3))]
            best, kept = (cur[0] if cur else before), True
            note += (f"; keep the current set-up: the best candidate's predicted gain {gain * 1e3:.1f} um does not "
                     f"exceed its uncertainty {gain_unc * 1e3:.1f} um")
    if progress is not None:  # the last report: the answer's own figure
        progress(RecommendProgress(n_eval, len(orients), n_kept, len(cands), time.monotonic() - t_start,
                                   best.reported_p95_mm))
    return Recommendation(best=best, before=before, ranked=ranked, n_points=m, n_region=n_region,
                          n_orientations=len(orients), n_orientations_kept=n_kept, n_settings=len(cands), note=note,
                          n_orientations_evaluated=n_eval, kept_current=kept, uses_uncertainty=uses_u,
                          n_out_of_domain=n_ood, top=top, gain=gain_pair)
