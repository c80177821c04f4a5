"""Rescan recommendation (ROS-free): which settings and head orientation minimise the predicted error in a region.

Search (exhaustive grid, deterministic):
- the region's processed points are subsampled to at most ``max_points`` (evenly spaced rows, deterministic);
- orientations: tilts about head X and head Y in ``linspace(-max_tilt, max_tilt, tilt_steps)`` and turns about head
  Z in ``linspace(-max_turn, max_turn, turn_steps)`` (defaults 3 × 3 × 3 = 27 orientations, identity included),
  each applied to the current head pose about the region centroid (``HeadPose.rotated(r, pivot=centroid)``);
- settings: the candidates given, or the scanner's 27 study configurations.
For each orientation the geometry-dependent features are recomputed (``FeatureContext.with_pose``), and for each
settings the settings features (``with_settings``); all candidates of one orientation go into one predict call.
A point is *covered* when lit and seen at non-grazing angles (acos(N·L) and acos(N·V) under the grazing
thresholds). Orientations covering less than ``min(min_coverage, current coverage)`` of the region are discarded
before any prediction. Candidates are ranked by the p95 of the predicted |error| (norm over x, y, z) over their
covered points, ties by the mean.

A time budget (``max_seconds``) stops the search after the orientation in progress; the current orientation is
always evaluated first, and the note says when the search was cut short.

Limits (honest): it ranks by the model's *predicted systematic* error only (no random noise, no occlusion by other
parts of the workpiece, no reachability of the pose); candidates far from the training domain are extrapolations;
the normals are those of the current scan.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from .geometry import HeadPose, matrix_to_quat
from .scanner import ScannerModel, ScanSettings

__all__ = [
    "Candidate",
    "RecommendCancelled",
    "RecommendProgress",
    "Recommendation",
    "coverage_mask",
    "orientation_grid",
    "recommend",
    "rotation_xyz",
]


@dataclass
class Candidate:
    """One evaluated set-up: settings and head rotation, predicted mean / p95 |error| (mm), coverage, score."""

    settings: ScanSettings
    rotation: np.ndarray          # 3x3, in the head frame, relative to the current head pose
    pose: HeadPose                # the resulting head pose (scan frame, mm)
    mean_mm: float
    p95_mm: float
    coverage: float

    @property
    def quaternion(self) -> np.ndarray:
        return matrix_to_quat(self.rotation)

    @property
    def score_mm(self) -> float:
        return self.p95_mm


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


def rotation_xyz(rx: float, ry: float, rz: float) -> np.ndarray:
    """R = Rz(rz) · Ry(ry) · Rx(rx) (radians), a rotation in the head frame."""
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    r_x = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    r_y = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    r_z = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return r_z @ r_y @ r_x


def orientation_grid(max_tilt: float, tilt_steps: int, max_turn: float, turn_steps: int) -> list[np.ndarray]:
    """Head-frame rotations of the search; ``max_* <= 0`` or 1 step → that axis is not searched."""
    tilts = np.linspace(-max_tilt, max_tilt, tilt_steps) if max_tilt > 0 and tilt_steps > 1 else np.zeros(1)
    turns = np.linspace(-max_turn, max_turn, turn_steps) if max_turn > 0 and turn_steps > 1 else np.zeros(1)
    return [rotation_xyz(a, b, c) for c in turns for a in tilts for b in tilts]


def coverage_mask(ctx: Any, grazing_incidence_deg: float, grazing_view_deg: float) -> np.ndarray:
    """Points lit and seen at non-grazing angles under the context's geometry."""
    n = np.asarray(ctx.normals, dtype=np.float64)
    cos_i = np.einsum("ij,ij->i", n, np.asarray(ctx.L, dtype=np.float64))
    cos_v = np.einsum("ij,ij->i", n, np.asarray(ctx.V, dtype=np.float64))
    return (cos_i > np.cos(np.radians(grazing_incidence_deg))) & (cos_v > np.cos(np.radians(grazing_view_deg)))


def _stats(pred_mm: np.ndarray, covered: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and p95 of the |error| norm over the covered points: pred (..., m, 3) → (...,) each (inf if none)."""
    e = np.sqrt(np.einsum("...ij,...ij->...i", pred_mm[..., covered, :], pred_mm[..., covered, :]))
    if e.shape[-1] == 0:
        inf = np.full(e.shape[:-1], np.inf)
        return inf, inf
    return e.mean(axis=-1), np.percentile(e, 95, axis=-1)


def recommend(model_set: Any, ctx: Any, rows: np.ndarray, before_features: np.ndarray, pose: HeadPose,
              scanner: ScannerModel, settings: ScanSettings, candidates: list[ScanSettings] | None = None, *,
              max_points: int = 2000, max_tilt: float = 0.2618, tilt_steps: int = 3, max_turn: float = 1.5708,
              turn_steps: int = 3, grazing_incidence_deg: float = 75.0, grazing_view_deg: float = 75.0,
              min_coverage: float = 0.95, batch_rows: int = 400_000,
              max_seconds: float | None = None,
              progress: Callable[[RecommendProgress], None] | None = None,
              cancelled: Callable[[], bool] | None = None) -> Recommendation:
    """Search settings × orientations for the region ``rows`` of a judged scan (see the module docstring).

    Args:
        model_set: inference.ModelSet (feature_names, predict in mm).
        ctx: FeatureContext of the judged scan's processed points.
        rows: region rows into ``ctx`` (non-empty).
        before_features: (M, F) the judged features of all rows (the "before" prediction uses them; the region
            subsample is predicted as its own cloud, like every candidate, so with a PointNet model "before" can
            differ slightly from the published deviations of the whole scan, but compares like with like).
        pose, scanner, settings: the current head pose (mm), scanner, settings.
        candidates: settings to try; None → ``scanner.study_configurations()``.
        max_seconds: time budget; the search stops (and says so in the note) once it is spent, after at least the
            current orientation (evaluated first).
        progress: called after each orientation with a :class:`RecommendProgress` (the ROS action's feedback).
        cancelled: polled before each orientation; true → :class:`RecommendCancelled` is raised.

    Raises:
        ValueError: empty region, or no orientation keeps the required coverage.
        RecommendCancelled: ``cancelled()`` became true.
    """
    from .features import REGISTRY, compute_features

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

    cov_before = coverage_mask(sub, grazing_incidence_deg, grazing_view_deg)
    pred_before = np.asarray(model_set.predict(before_features[rows]), dtype=np.float64)
    mean_b, p95_b = _stats(pred_before, cov_before)
    before = Candidate(settings, np.eye(3), pose, float(mean_b), float(p95_b), float(cov_before.mean()))
    need = min(min_coverage, before.coverage) - 1e-12

    dep = [j for j, n in enumerate(names) if "settings" in tuple(REGISTRY.get(n).inputs)]
    dep_names = [names[j] for j in dep]
    orients = orientation_grid(max_tilt, tilt_steps, max_turn, turn_steps)
    # The current orientation first: it is always evaluated, whatever the time budget.
    orients.sort(key=lambda r: not np.allclose(r, np.eye(3)))
    t_start = time.monotonic()
    ranked: list[Candidate] = []
    n_kept = n_eval = 0
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
        cov = coverage_mask(ctx_o, grazing_incidence_deg, grazing_view_deg)
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
        pred = np.concatenate([np.asarray(model_set.predict_batch(X[i:i + step]), dtype=np.float64)
                               for i in range(0, len(X), step)])
        means, p95s = _stats(pred, cov)
        for k, s in enumerate(cands):
            ranked.append(Candidate(s, r, pose_o, float(means[k]), float(p95s[k]), float(cov.mean())))
        best_p95 = min(best_p95, float(np.min(p95s)))
    if progress is not None:
        progress(RecommendProgress(n_eval, len(orients), n_kept, len(cands), time.monotonic() - t_start, best_p95))
    if not ranked:
        raise ValueError(f"no orientation keeps the coverage >= {need:.3f} of the region")
    ranked.sort(key=lambda c: (c.p95_mm, c.mean_mm))
    note = f"{len(orients)} orientations ({n_kept} kept) x {len(cands)} settings on {m} points"
    if n_eval < len(orients):
        note += (f"; time budget of {max_seconds:g} s spent: search stopped after {n_eval} of {len(orients)} "
                 "orientations")
    if n_region > m:
        note += f" (region of {n_region} points subsampled, evenly spaced)"
    return Recommendation(best=ranked[0], before=before, ranked=ranked, n_points=m, n_region=n_region,
                          n_orientations=len(orients), n_orientations_kept=n_kept, n_settings=len(cands), note=note,
                          n_orientations_evaluated=n_eval)
