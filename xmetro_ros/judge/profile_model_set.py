"""A profile model set on disk (``model.onnx`` + ``card.json``, written by ``learn.profile_model``), run with ONNX
Runtime: per point of a profile, d along the outward in-plane normal and its 95 % half-width U, and both per axis
of the sensor frame (x along the line, z the range axis; y carries none: profile points lie in the laser plane).
Lengths mm, angles deg.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["BIN_DEG", "FORMAT", "N_BINS", "ProfileModelError", "ProfileModelSet", "angle_bins"]

FORMAT = "xmetro-profile-model/1"
BIN_DEG = 10.0  # U's bins of |in-plane incidence|, the one rule for calibration (learn) and prediction (here)
N_BINS = 9  # 0-90°; 90° and beyond fall in the last bin


def angle_bins(inc_deg: np.ndarray) -> np.ndarray:
    """10° bin index (0..8) of |in-plane incidence| (deg); 90° and beyond fall in the last bin."""
    a = np.abs(np.asarray(inc_deg, dtype=np.float64))
    return np.clip(np.floor(a / BIN_DEG), 0, N_BINS - 1).astype(np.int64)


class ProfileModelError(ValueError):
    """A profile model directory that is missing, of another format or inconsistent."""


class ProfileModelSet:
    """Loaded profile model (see module doc). ``feature_names`` are the columns ``predict`` expects."""

    def __init__(self, model_dir: str | Path, threads: int = 1) -> None:
        import onnxruntime as ort

        d = Path(model_dir)
        try:
            self.card: dict[str, Any] = json.loads((d / "card.json").read_text())
        except (OSError, ValueError) as e:
            raise ProfileModelError(f"{d}: cannot read card.json: {e}") from e
        if self.card.get("format") != FORMAT:
            raise ProfileModelError(f"{d}: card format {self.card.get('format')!r}, expected {FORMAT!r}")
        self.feature_names: list[str] = list(self.card["features"])
        hw = self.card["uncertainty"]["half_width_mm"]
        self.half_width_mm = np.array([np.nan if v is None else float(v) for v in hw], dtype=np.float64)
        if len(self.half_width_mm) != N_BINS:
            raise ProfileModelError(f"{d}: the card has {len(self.half_width_mm)} U bins, expected {N_BINS}")
        if "inc_plane" not in self.feature_names:
            raise ProfileModelError(f"{d}: the card's features {self.feature_names} lack inc_plane (U's bins)")
        self._inc = self.feature_names.index("inc_plane")
        so = ort.SessionOptions()
        so.intra_op_num_threads = max(1, threads)
        try:
            self._sess = ort.InferenceSession(str(d / "model.onnx"), so, providers=["CPUExecutionProvider"])
        except Exception as e:  # onnxruntime raises its own types for a missing or corrupt graph
            raise ProfileModelError(f"{d}: cannot load model.onnx: {e}") from e
        self.model_dir = d

    def _check(self, X: np.ndarray) -> np.ndarray:
        X = np.ascontiguousarray(X, dtype=np.float32)
        if X.ndim != 2 or X.shape[1] != len(self.feature_names):
            raise ValueError(f"X must be (M, {len(self.feature_names)}) ({', '.join(self.feature_names)}), "
                             f"got {X.shape}")
        if not np.all(np.isfinite(X)):
            raise ValueError("X holds non-finite features")
        return X

    def predict(self, X: np.ndarray) -> np.ndarray:
        """d (M,) mm along the outward normal (nominal − measured)."""
        X = self._check(X)
        if len(X) == 0:
            return np.zeros(0)
        return self._sess.run(None, {"X": X})[0].reshape(-1).astype(np.float64)

    def uncertainty(self, X: np.ndarray) -> np.ndarray:
        """U (M,) mm (NaN where the card's bin was never calibrated)."""
        X = self._check(X)
        return self.half_width_mm[angle_bins(X[:, self._inc])]

    def in_domain(self, X: np.ndarray, margin: float = 0.05) -> np.ndarray:
        """(M,) True where every feature lies inside the training range recorded in the card, widened by
        ``margin`` of its span (a point outside is extrapolation: its d and U are not backed by the calibration)."""
        X = self._check(X)
        ok = np.ones(len(X), dtype=bool)
        for j, name in enumerate(self.feature_names):
            lo, hi = self.card.get("feature_ranges", {}).get(name, (-np.inf, np.inf))
            w = margin * (hi - lo) if np.isfinite(hi - lo) else 0.0
            ok &= (X[:, j] >= lo - w) & (X[:, j] <= hi + w)
        return ok

    def publish(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What the product publishes per point: ``(d, U, out_of_domain)`` with d and U NaN where the point is
        outside the calibration's feature ranges (:meth:`in_domain`) or its U bin was never calibrated — a point
        without a U that holds gets no d either (never a silent extrapolation)."""
        d = self.predict(X)
        U = self.uncertainty(X)
        ood = ~self.in_domain(X)
        bad = ood | ~np.isfinite(U)
        d[bad] = np.nan
        U = np.where(bad, np.nan, U)
        return d, U, ood

    @staticmethod
    def per_axis(values: np.ndarray, normals: np.ndarray, absolute: bool = False) -> np.ndarray:
        """(M, 3) x, y, z components of a normal quantity (d: signed; U: ``absolute``) for in-plane normals
        (M, 2) (n_x, n_z)."""
        n = np.asarray(normals, dtype=np.float64)
        n = np.abs(n) if absolute else n
        v = np.asarray(values, dtype=np.float64)
        return np.column_stack([v * n[:, 0], np.zeros(len(v)), v * n[:, 1]])
