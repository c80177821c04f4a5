"""The loop's model of the current feature set: a fast point-wise family retrained on the training part of the
input, or a given model directory (``ModelSet``). Errors in mm, features in study units.

The retrained family is CatBoost with LEARN's conventions (one regressor per axis on µm targets), so that LEARN's
ONNX exporter turns the augmented model into a model set the node loads.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["AxisModel", "fit_family", "GivenModel", "LOOP_FAMILIES"]

LOOP_FAMILIES = ("catboost",)
TARGET_SCALE = 1000.0  # mm → µm, as LEARN's families (xmetro_ros.learn.families.TARGET_SCALE)


@dataclass
class AxisModel:
    """One fitted regressor per axis (x, y, z) on µm targets; ``predict`` returns mm."""

    family: str
    estimators: list[Any]
    feature_names: list[str]
    params: dict = field(default_factory=dict)

    def predict(self, X: np.ndarray) -> np.ndarray:
        X = np.asarray(X, dtype=np.float32)
        if X.ndim != 2 or X.shape[1] != len(self.feature_names):
            raise ValueError(f"X must be (M, {len(self.feature_names)}), got {X.shape}")
        return np.stack([e.predict(X) for e in self.estimators], axis=1) / TARGET_SCALE


def fit_family(
    family: str, X: np.ndarray, y: np.ndarray, feature_names: list[str], *, seed: int = 0, iterations: int = 300,
    depth: int = 6, learning_rate: float = 0.1, threads: int = 2,
) -> AxisModel:
    """Fit ``family`` per axis on X (M, F) → y (M, 3) mm. Only CatBoost is offered (fast, exportable)."""
    if family not in LOOP_FAMILIES:
        raise ValueError(f"loop model family {family!r} is not supported; choose one of {LOOP_FAMILIES}")
    X = np.asarray(X, dtype=np.float32)
    y = np.asarray(y, dtype=float)
    if len(X) < 10:
        raise ValueError(f"too few training points to fit the model: {len(X)}")
    from catboost import CatBoostRegressor

    params = {"iterations": iterations, "depth": depth, "learning_rate": learning_rate, "loss_function": "RMSE"}
    ests = []
    for a in range(3):
        est = CatBoostRegressor(random_seed=seed, verbose=0, thread_count=threads, allow_writing_files=False,
                                **params)
        est.fit(X, y[:, a] * TARGET_SCALE)
        ests.append(est)
    return AxisModel(family, ests, list(feature_names), params)


@dataclass
class GivenModel:
    """A model directory loaded with ``xmetro_ros.inference.ModelSet`` (features must be computable here)."""

    model_set: Any

    @property
    def feature_names(self) -> list[str]:
        return list(self.model_set.feature_names)

    def predict(self, X: np.ndarray) -> np.ndarray:
        return np.asarray(self.model_set.predict(np.asarray(X, dtype=np.float32)), dtype=float)
