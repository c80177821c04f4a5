"""Judged-scan history and the ROS-free body of ``~/explain`` (SHAP values for points of a judged scan).

The node keeps the last few judged scans (:class:`ScanHistory`, bounded). A request picks a scan (stamp, 0 = the
latest), points (flat indices, or a sphere region in the scan frame, or every processed point), and axes; the
answer holds, for every model feature (and, for a PointNet model, the ``set_context`` player) and every requested
axis, the SHAP values (``attribution.explain_in_cloud``), base values, the features, the predictions
(= base + Σ SHAP = the published deviations) and the mean |SHAP| per feature over the explained points.
Units: mm inside, metres in the response (the node converts).
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["JudgedScan", "ScanHistory", "ServiceError", "axes_from_mask", "explain_rows", "select_rows"]

AXIS_NAMES = ("x", "y", "z")


class ServiceError(ValueError):
    """A service request that cannot be answered; the message is returned with success = false."""


@dataclass
class JudgedScan:
    """What the services need of a judged scan (mm, scan frame).

    Attributes:
        stamp_ns, frame_id: the scan's header.
        n_points: points in the (possibly decimated) cloud, = width × height.
        index: (M,) flat indices of the processed (kept) points.
        points: (M, 3) mm those points.
        features: (M, F) float32 model features; predictions (M, 3) mm (stored as float32: only their
            finiteness is used).
        context: features.FeatureContext of those points (for the recommender).
        settings, pose, scanner_id, model_id: how it was taken and judged.
        uncertainty: (M, 3) mm published U of those points (None / NaN: none); kept for reference only, the
            explainer recomputes U from the features.
        surface_class: (M,) int8 surface class whose multipliers each point's U took (None: the card has none);
            the explainer of U keeps each point's class.
        noise: (M,) float64 measured noise (mm, along the normal) each point's U took (None: the card's U does not
            use it; NaN: none for that point); the explainer of U keeps it with the class.
        tilt: (M, 3) float64 measured tilt noise (radians) each point's along-normal U took (None: none taken).
    """

    stamp_ns: int
    frame_id: str
    n_points: int
    index: np.ndarray
    points: np.ndarray
    features: np.ndarray
    predictions: np.ndarray
    context: Any
    settings: Any
    pose: Any
    scanner_id: str
    model_id: str
    uncertainty: np.ndarray | None = None
    cad_pose: np.ndarray | None = None  # (4, 4) mm, part → scan frame, of the CAD map of this scan (None: no CAD)
    surface_class: np.ndarray | None = None
    noise: np.ndarray | None = None
    tilt: np.ndarray | None = None

    def __post_init__(self) -> None:
        # Kept for every judged scan in the history: only what the services need, compactly.
        self.predictions = np.asarray(self.predictions, dtype=np.float32)
        if self.uncertainty is not None:
            self.uncertainty = np.asarray(self.uncertainty, dtype=np.float32)
        self.index = np.asarray(self.index, dtype=np.int64)

    @property
    def ok_rows(self) -> np.ndarray:
        """Rows with a finite prediction (only those can be explained)."""
        return np.flatnonzero(np.isfinite(self.predictions).all(axis=1))

    @property
    def row_of(self) -> np.ndarray:
        """(n_points,) row of each flat cloud index, -1 where there is no explainable point."""
        ok = self.ok_rows
        row_of = np.full(self.n_points, -1, dtype=np.int64)
        row_of[self.index[ok]] = ok
        return row_of


class ScanHistory:
    """The last ``maxlen`` judged scans, thread-safe."""

    def __init__(self, maxlen: int = 3) -> None:
        self._scans: deque[JudgedScan] = deque(maxlen=maxlen)
        self._lock = threading.Lock()

    def add(self, judged: JudgedScan) -> None:
        with self._lock:
            self._scans.append(judged)

    def __len__(self) -> int:
        return len(self._scans)

    def get(self, stamp_ns: int = 0) -> JudgedScan:
        """The scan stamped ``stamp_ns`` (0 = the latest). Raises ServiceError when not kept."""
        with self._lock:
            scans = list(self._scans)
        if not scans:
            raise ServiceError("no scan judged yet")
        if stamp_ns == 0:
            return scans[-1]
        for s in reversed(scans):
            if s.stamp_ns == stamp_ns:
                return s
        kept = ", ".join(str(s.stamp_ns) for s in scans)
        raise ServiceError(f"no judged scan stamped {stamp_ns} ns is kept (kept: {kept})")


def axes_from_mask(mask: int) -> tuple[int, ...]:
    """Axis indices from an AXIS_X=1 | AXIS_Y=2 | AXIS_Z=4 mask (0 = all). Raises ServiceError on bad bits."""
    if mask == 0:
        return (0, 1, 2)
    if mask & ~7:
        raise ServiceError(f"axes mask {mask} has bits other than AXIS_X=1, AXIS_Y=2, AXIS_Z=4")
    return tuple(i for i in range(3) if mask & (1 << i))


def select_rows(judged: JudgedScan, indices: np.ndarray, center_mm: np.ndarray | None, radius_mm: float,
                cap: int) -> tuple[np.ndarray, str]:
    """Rows of ``judged`` for a request, and a note.

    Explicit ``indices`` (flat indices into the cloud) must all be processed points and at most ``cap`` of them
    (ServiceError otherwise). A region (``radius_mm`` > 0 around ``center_mm``) or, with radius 0, every processed
    point: when more than ``cap``, an evenly spaced deterministic subset of ``cap`` rows is taken (said in the note).
    """
    indices = np.asarray(indices, dtype=np.int64)
    ok_rows = judged.ok_rows
    if len(indices):
        if len(indices) > cap:
            raise ServiceError(f"{len(indices)} indices requested, more than the cap of {cap} points")
        bad = (indices < 0) | (indices >= judged.n_points)
        if bad.any():
            raise ServiceError(f"indices out of range [0, {judged.n_points}): {indices[bad][:5].tolist()}")
        rows = judged.row_of[indices]
        if (rows < 0).any():
            raise ServiceError(f"indices without a prediction (invalid or outlier points): "
                               f"{indices[rows < 0][:5].tolist()}")
        return rows, ""
    if radius_mm < 0 or not np.isfinite(radius_mm):
        raise ServiceError(f"region radius must be >= 0, got {radius_mm}")
    if radius_mm > 0:
        d2 = np.sum((judged.points[ok_rows] - np.asarray(center_mm, dtype=np.float64)) ** 2, axis=1)
        rows = ok_rows[d2 <= radius_mm * radius_mm]
        if len(rows) == 0:
            raise ServiceError(f"the region (radius {radius_mm * 1e-3:g} m) holds no processed point")
    else:
        rows = ok_rows
    note = ""
    if len(rows) > cap:
        note = f"region has {len(rows)} points: explained an evenly spaced subset of {cap}"
        rows = rows[np.linspace(0, len(rows) - 1, cap).round().astype(np.int64)]
    return rows, note


def explain_rows(model_set: Any, judged: JudgedScan, rows: np.ndarray, axes: tuple[int, ...],
                 output: str = "error") -> dict[str, Any]:
    """SHAP explanation of the predictions of ``rows`` of ``judged`` (mm): base (A,), shap (P, F', A), predictions
    (P, A) (the model's target t = nominal − measured; ``~/explain`` publishes them with the sign of the published
    deviations, ``scan.targets.published_deviation``), player values X (P, F'), names and units of the F' players,
    mean |SHAP| (F', A) over the explained points, point indices (P,).

    The players are the model's features, plus ``set_context`` (the other points of the point's PointNet set; its
    value is how many distinct other points that set holds) when the model has a set member
    (``attribution.explain_in_cloud``), plus ``surface_class`` (its value: the point's class index) when U is
    explained for a card calibrated per class (the player also carries the point's measured noise where the card's
    U takes it: both switch on together), plus ``along_normal`` (its value: 1 where the card's along-normal block
    carried the point's d and U onto its measured normal, :mod:`.along_normal`) when the card has that block.

    ``output="uncertainty"`` explains the published expanded uncertainty U instead of the error (which features
    make a point uncertain): predictions = base + Σ SHAP = U. ServiceError when the model set has no calibration.
    """
    from .attribution import ALONG_NORMAL, SET_CONTEXT, SURFACE_CLASS, explain_in_cloud

    feats = judged.features
    finite = np.isfinite(feats).all(axis=1)
    # The model predicted the finite rows together, in order (inference.ModelSet.predict): explain in that cloud.
    cloud_row = np.cumsum(finite) - 1
    if output == "uncertainty" and not getattr(model_set, "calibrated", False):
        raise ServiceError(f"model set {getattr(model_set, 'id', '?')!r} has no uncertainty calibration: "
                           "no U to explain")
    surf, noise = judged.surface_class, judged.noise
    surf_f = None if surf is None else np.asarray(surf)[finite]
    noise_f = None if noise is None else np.asarray(noise)[finite]
    along_rows = getattr(model_set, "along_normal_rows", None)
    tilt_f = None if judged.tilt is None else np.asarray(judged.tilt)[finite]
    along = None if along_rows is None else along_rows(feats[finite], surf_f, noise_f, judged.settings, tilt=tilt_f)
    res = explain_in_cloud(model_set, feats[finite], cloud_row[rows], None, axes=axes, output=output,
                           surface_class=surf_f, noise=noise_f, along=along)
    X = feats[rows].astype(np.float64)
    names = list(model_set.feature_names)
    units = list(model_set.feature_units)
    if model_set.has_sets:  # explain_in_cloud added the set-context player last
        from .pointsets import set_membership

        _, set_of = set_membership(int(finite.sum()), model_set.set_size, model_set.partition_seed)
        sizes = np.bincount(set_of)
        X = np.column_stack([X, sizes[set_of[cloud_row[rows]]] - 1.0])
        names.append(SET_CONTEXT)
        units.append("points")
    if SURFACE_CLASS in res.feature_names:  # U explained with the points' classes: the class is a player
        X = np.column_stack([X, np.asarray(surf)[rows].astype(np.float64)])
        names.append(SURFACE_CLASS)
        units.append("class index (judge/surface_class.py; -1 none)")
    if along is not None:  # the card carries d and U onto the normal: its own player, last
        X = np.column_stack([X, along.use[cloud_row[rows]].astype(np.float64)])
        names.append(ALONG_NORMAL)
        units.append("1: carried onto the measured normal (judge/along_normal.py), 0: the model's output")
    shap_vals = np.asarray(res.shap, dtype=np.float64)
    return {
        "base_values": np.asarray(res.base_values, dtype=np.float64),
        "shap": shap_vals,
        "predictions": np.asarray(res.predictions, dtype=np.float64),
        "features": X,
        "feature_names": names,
        "feature_units": units,
        "mean_abs_shap": np.abs(shap_vals).mean(axis=0),
        "point_indices": np.asarray(judged.index, dtype=np.int64)[rows],
        "axis_names": [AXIS_NAMES[a] for a in axes],
        "output": output,
    }
