"""The loop's model of the current feature set: a fast point-wise family retrained on the training part of the
input, or a given model directory (``ModelSet``). Errors in mm, features in study units.

The retrained family is CatBoost fitted by LEARN's ``fit_model`` (one regressor per axis), so that LEARN's
``export_model_set`` turns the augmented model into a model set the node loads.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["LOOP_FAMILIES", "AxisModel", "ConstantAxis", "GivenModel", "NormalCorrector", "fit_family",
           "fit_normal_corrector"]

LOOP_FAMILIES = ("catboost",)


@dataclass
class ConstantAxis:
    """The model of an axis whose training target is one value (the y axis of laser-line profiles: their points and
    errors lie in the laser plane, y = 0): predicts that value (mm). A boosted family cannot fit a constant."""

    family: str
    axes: tuple[int, ...]
    value: float

    def predict(self, X: np.ndarray, groups: np.ndarray | None = None) -> np.ndarray:
        return np.full((len(X), 1), self.value)


@dataclass
class AxisModel:
    """One LEARN ``FittedModel`` per axis (x, y, z); ``predict`` returns (M, 3) mm."""

    family: str
    models: list[Any]
    feature_names: list[str]
    params: dict = field(default_factory=dict)

    def predict(self, X: np.ndarray) -> np.ndarray:
        X = np.asarray(X, dtype=np.float32)
        if X.ndim != 2 or X.shape[1] != len(self.feature_names):
            raise ValueError(f"X must be (M, {len(self.feature_names)}), got {X.shape}")
        return np.concatenate([m.predict(X) for m in self.models], axis=1)


def fit_family(
    family: str, X: np.ndarray, y: np.ndarray, feature_names: list[str], *, seed: int = 0, iterations: int = 300,
    depth: int = 6, learning_rate: float = 0.1, threads: int = 2,
) -> AxisModel:
    """Fit ``family`` per axis with LEARN's ``fit_model`` (fixed hyper-parameters, no search) on X (M, F) → y (M, 3)
    mm; an axis whose target is constant (profiles: y) gets a ``ConstantAxis``. Only CatBoost is offered here (fast,
    exported by LEARN's ONNX exporter)."""
    from ..learn.train import fit_model

    if family not in LOOP_FAMILIES:
        raise ValueError(f"loop model family {family!r} is not supported; choose one of {LOOP_FAMILIES}")
    X = np.asarray(X, dtype=np.float32)
    y = np.asarray(y, dtype=float)
    if len(X) < 10:
        raise ValueError(f"too few training points to fit the model: {len(X)}")
    params = {"iterations": iterations, "depth": depth, "learning_rate": learning_rate}
    models = [ConstantAxis(family, (a,), float(y[0, a])) if np.ptp(y[:, a]) == 0 else
              fit_model(family, X, y[:, a], seed=seed, axes=(a,), params=params, threads=threads) for a in range(3)]
    return AxisModel(family, models, list(feature_names), params)


@dataclass
class GivenModel:
    """A model directory loaded with ``xmetro_ros.judge.inference.ModelSet`` (features must be computable here)."""

    model_set: Any

    @property
    def feature_names(self) -> list[str]:
        return list(self.model_set.feature_names)

    def predict(self, X: np.ndarray) -> np.ndarray:
        return np.asarray(self.model_set.predict(np.asarray(X, dtype=np.float32)), dtype=float)


@dataclass
class NormalCorrector:
    """A residual corrector of a given model along the nominal normal: one regressor of the normal residual (mm)
    on the added variables; its correction is (predicted normal residual) × n. Sphere and cylinder errors lie along
    the normal, so one scalar target carries them; per axis, the same variable would have to be learnt with the
    normal's sign for every head orientation, from the few training clouds."""

    model: Any
    feature_names: list[str]

    def predict(self, X: np.ndarray, normals: np.ndarray) -> np.ndarray:
        rn = self.model.predict(np.asarray(X, dtype=np.float32)).reshape(-1)
        return rn[:, None] * np.asarray(normals, dtype=float)


def fit_normal_corrector(
    family: str, X: np.ndarray, normal_residual: np.ndarray, feature_names: list[str], *, seed: int = 0,
    iterations: int = 300, depth: int = 6, learning_rate: float = 0.1, threads: int = 2,
) -> NormalCorrector:
    """Fit ``family`` (LEARN's ``fit_model``, fixed hyper-parameters) of the normal residual (mm) on X (M, F)."""
    from ..learn.train import fit_model

    if family not in LOOP_FAMILIES:
        raise ValueError(f"loop model family {family!r} is not supported; choose one of {LOOP_FAMILIES}")
    params = {"iterations": iterations, "depth": depth, "learning_rate": learning_rate}
    m = fit_model(family, np.asarray(X, dtype=np.float32), np.asarray(normal_residual, dtype=float), seed=seed,
                  axes=(0,), params=params, threads=threads)
    return NormalCorrector(m, list(feature_names))
