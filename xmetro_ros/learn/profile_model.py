"""The profile model: per-point deviation d along the surface normal and its 95 % half-width U, from features a
single laser-line profile gives (``calibrate.profile_table.PROFILE_FEATURES``). One estimator, fit/predict.

- d: CatBoost regression of the normal deviation (nominal − measured, trained in µm, exported to ONNX in mm);
  per axis d × (n_x, 0, n_z). On a sphere every error lies along the normal, so one scalar target carries both
  axes of the laser plane; fitting x and z separately would learn the normal's sign as well.
- U: split-conformal half-widths (crepes ``ConformalRegressor``, Mondrian by 10° bins of |in-plane incidence|),
  cross-fitted over **positions**: the calibration positions are split into ``folds``; each fold's residuals
  come from a model trained without any repeat of its positions, so U is the width of the error at a position
  the model has not seen (repeats share their systematic error: residuals on repeats of training positions
  would understate it). Per axis U × |n_axis|: a per-axis interval then holds exactly when the normal one does.
- The finite-sample quantile needs ``MIN_BIN_POINTS`` residuals per bin; a thinner bin takes the widest half-width
  of the bins around it (an envelope, documented in the card); a bin no calibration point reached is refused
  (NaN U) at prediction.

Lengths mm (features: u, w mm; inc_plane deg; arc_curvature 1/mm).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..judge.profile_model_set import BIN_DEG, FORMAT, N_BINS, angle_bins

__all__ = ["MIN_BIN_POINTS", "PROFILE_MODEL_FORMAT", "ProfileModel", "angle_bins"]

PROFILE_MODEL_FORMAT = FORMAT
MIN_BIN_POINTS = 200
INC_COLUMN = 2  # inc_plane in PROFILE_FEATURES


@dataclass
class ProfileModel:
    """CatBoost d + position-cross-fitted Mondrian conformal U (module doc)."""

    iterations: int = 1000
    depth: int = 8
    learning_rate: float = 0.1
    folds: int = 4
    confidence: float = 0.95
    seed: int = 0
    threads: int = 2
    feature_names: list[str] = field(default_factory=list)
    regressor_: Any = None
    half_width_mm_: np.ndarray | None = None
    bin_counts_: np.ndarray | None = None
    bin_source_: list[str] = field(default_factory=list)
    feature_ranges_: dict[str, list[float]] = field(default_factory=dict)

    def _new(self) -> Any:
        from catboost import CatBoostRegressor

        return CatBoostRegressor(iterations=self.iterations, depth=self.depth, learning_rate=self.learning_rate,
                                 loss_function="RMSE", random_seed=self.seed, thread_count=self.threads, verbose=0,
                                 allow_writing_files=False)

    def fit(self, X: np.ndarray, deviation_mm: np.ndarray, positions: np.ndarray, *, fit_rows: np.ndarray | None = None,
            calibration_rows: np.ndarray | None = None, feature_names: list[str] | None = None) -> ProfileModel:
        """Fit d on ``fit_rows`` (default all) and calibrate U on ``calibration_rows`` (default all) of X (M, F)
        → deviation (M,) mm; ``positions`` (M,) the position id of each row (repeats share it)."""
        X = np.asarray(X, dtype=np.float32)
        y = np.asarray(deviation_mm, dtype=np.float64) * 1000.0
        pos = np.asarray(positions)
        if X.ndim != 2 or len(X) != len(y) or len(pos) != len(y):
            raise ValueError(f"X (M, F), deviation (M,) and positions (M,) must agree: {X.shape}, {y.shape}, "
                             f"{pos.shape}")
        if not np.all(np.isfinite(X)) or not np.all(np.isfinite(y)):
            raise ValueError("non-finite features or deviations")
        fr = np.ones(len(y), bool) if fit_rows is None else np.asarray(fit_rows, bool)
        cr = np.ones(len(y), bool) if calibration_rows is None else np.asarray(calibration_rows, bool)
        self.feature_names = list(feature_names) if feature_names is not None else [f"f{i}" for i in
                                                                                     range(X.shape[1])]
        upos = np.unique(pos[fr | cr])
        if len(upos) < self.folds:
            raise ValueError(f"{len(upos)} positions: fewer than the {self.folds} folds of the calibration")
        rng = np.random.default_rng(self.seed)
        fold_of = dict(zip(upos.tolist(), rng.permutation(len(upos)) % self.folds, strict=False))
        fold = np.array([fold_of.get(p, -1) for p in pos.tolist()])
        resid = np.full(len(y), np.nan)
        for k in range(self.folds):
            m = self._new().fit(X[fr & (fold != k)], y[fr & (fold != k)])
            at = cr & (fold == k)
            resid[at] = y[at] - m.predict(X[at])
        self._calibrate(np.abs(resid[cr]) / 1000.0, angle_bins(X[cr, INC_COLUMN]))
        self.regressor_ = self._new().fit(X[fr], y[fr])
        self.feature_ranges_ = {n: [float(X[fr, j].min()), float(X[fr, j].max())]
                                for j, n in enumerate(self.feature_names)}
        return self

    def fit_regressor(self, X: np.ndarray, deviation_mm: np.ndarray) -> ProfileModel:
        """Fit d only (no U) on all rows of X (M, F) → deviation (M,) mm: for comparisons such as a model trained
        without some positions."""
        self.regressor_ = self._new().fit(np.asarray(X, dtype=np.float32),
                                          np.asarray(deviation_mm, dtype=np.float64) * 1000.0)
        return self

    def _calibrate(self, abs_resid_mm: np.ndarray, bins: np.ndarray) -> None:
        from crepes import ConformalRegressor

        counts = np.bincount(bins, minlength=N_BINS)
        hw = np.full(N_BINS, np.nan)
        for b in range(N_BINS):
            if counts[b] >= MIN_BIN_POINTS:
                cr = ConformalRegressor().fit(abs_resid_mm[bins == b])
                iv = cr.predict_int(np.zeros(1), confidence=self.confidence)
                hw[b] = float(iv[0, 1])
        src = ["own" if np.isfinite(hw[b]) else "" for b in range(N_BINS)]
        for b in range(N_BINS):  # a thin bin borrows the widest neighbour that has enough points
            if counts[b] and not np.isfinite(hw[b]):
                near = [hw[j] for j in (b - 1, b + 1) if 0 <= j < N_BINS and np.isfinite(hw[j])]
                if near:
                    hw[b] = max(near)
                    src[b] = "envelope of neighbours"
        self.half_width_mm_ = hw
        self.bin_counts_ = counts
        self.bin_source_ = src

    def predict(self, X: np.ndarray) -> np.ndarray:
        """d (M,) mm along the outward normal (nominal − measured)."""
        if self.regressor_ is None:
            raise RuntimeError("ProfileModel is not fitted")
        return np.asarray(self.regressor_.predict(np.asarray(X, dtype=np.float32)), dtype=np.float64) / 1000.0

    def uncertainty(self, X: np.ndarray) -> np.ndarray:
        """U (M,) mm, the 95 % half-width of the normal deviation about d (NaN in a bin never calibrated)."""
        if self.half_width_mm_ is None:
            raise RuntimeError("ProfileModel is not fitted")
        return self.half_width_mm_[angle_bins(np.asarray(X)[:, INC_COLUMN])]

    def card(self) -> dict[str, Any]:
        """What the exported model set records about the estimator and its calibration."""
        assert self.half_width_mm_ is not None and self.bin_counts_ is not None
        return {
            "format": PROFILE_MODEL_FORMAT,
            "features": list(self.feature_names),
            "feature_ranges": self.feature_ranges_,
            "target": "deviation along the outward in-plane normal, nominal - measured, mm; per axis d * (n_x, 0, n_z)",
            "regressor": {"family": "catboost", "iterations": self.iterations, "depth": self.depth,
                          "learning_rate": self.learning_rate, "seed": self.seed},
            "uncertainty": {
                "method": "split-conformal (crepes ConformalRegressor), Mondrian by |inc_plane| bins, residuals "
                          f"cross-fitted over {self.folds} folds of positions (no repeat of a calibration position "
                          "in its model's training)",
                "confidence": self.confidence, "bin_deg": BIN_DEG,
                "half_width_mm": [None if not np.isfinite(v) else float(v) for v in self.half_width_mm_],
                "calibration_points": [int(c) for c in self.bin_counts_],
                "source": list(self.bin_source_), "min_bin_points": MIN_BIN_POINTS,
            },
        }

    def export(self, out_dir: str | Path, X_check: np.ndarray, extra_card: dict[str, Any] | None = None) -> Path:
        """Write ``model.onnx`` (X (M, F) float32 → y (M, 1) mm) and ``card.json``. The graph is run by ONNX Runtime
        on ``X_check`` and must give the fitted regressor's d within 1e-4 µm + float32 rounding (else
        RuntimeError); the largest difference is in the card. Returns the directory."""
        import onnx
        import onnxruntime as ort

        from .export import export_pointwise

        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        model = export_pointwise("catboost", self.regressor_, len(self.feature_names))
        onnx.save(model, str(out / "model.onnx"))
        Xc = np.asarray(X_check, dtype=np.float32)
        sess = ort.InferenceSession(str(out / "model.onnx"), providers=["CPUExecutionProvider"])
        got = sess.run(None, {"X": Xc})[0].reshape(-1).astype(np.float64)
        diff = float(np.max(np.abs(got - self.predict(Xc)))) if len(Xc) else 0.0
        if diff > 1e-6:  # mm: 1 nm; float32 output of values of tens of µm rounds at ~1e-9 mm
            raise RuntimeError(f"the exported ONNX graph differs from the fitted model by {diff * 1000:.3g} µm")
        card = self.card()
        card["onnx_check"] = {"rows": len(Xc), "max_abs_diff_mm": diff}
        card.update(extra_card or {})
        (out / "card.json").write_text(json.dumps(card, indent=1))
        return out
