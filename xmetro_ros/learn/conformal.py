"""The split-conformal quantile every calibration of the package takes (crepes), in a module of its own so that the
calibrations built on it (``uncertainty``, ``along_normal``) import it without importing each other."""

from __future__ import annotations

import numpy as np

__all__ = ["conformal_multiplier"]


def conformal_multiplier(residuals: np.ndarray, sigmas: np.ndarray, confidence: float = 0.95) -> float:
    """crepes' normalized split-conformal half-width for σ̂ = 1: the finite-sample quantile of |r| / σ̂ at level
    ⌈(n + 1)·confidence⌉ / n (inf when n is too small for that level)."""
    from crepes import ConformalRegressor

    cr = ConformalRegressor().fit(residuals=np.asarray(residuals, np.float64), sigmas=np.asarray(sigmas, np.float64))
    return float(cr.predict_int(y_hat=np.zeros(1), sigmas=np.ones(1), confidence=confidence)[0, 1])
