"""σ of U where the scan's own noise is measured: the larger of the model's σ̂ and the measured noise projected on
each axis.

A point of an organized scan has a measured noise scale s along its normal (:mod:`xmetro_ros.preprocess.noise`);
projected on axis a it is s·|N_a| (N the unit normal, the features ``N_x``, ``N_y``, ``N_z``). Cards calibrated
with it (``uncertainty.conditional.by_surface.noise``) take σ_a = max(σ̂_a, s·|N_a|) for such points, with their
surface class's multipliers calibrated on the same σ; a point without a measured scale (an unorganized scan, a
hole's or the border's points) takes σ̂ and the all-class multipliers, calibrated on σ̂ alone. Why the larger and
not a sum: σ̂ already carries the noise where the model judged it right, and the model's error besides; the
measured scale is a floor where σ̂ fell short (on a part the model never saw, see the noise module). The same
function serves calibration and inference, so the multipliers are calibrated on the σ they multiply.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..compute import threads as _threads  # noqa: F401 - the threading layer, before any parallel kernel runs

__all__ = ["NORMAL_FEATURES", "effective_sigma"]

#: The feature columns of the unit normal (judge/features.py).
NORMAL_FEATURES = ("N_x", "N_y", "N_z")


def effective_sigma(sig: np.ndarray, normals: np.ndarray, surface_class: np.ndarray, noise: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """(σ (M, 3) float64, class (M,) int8) for U: max(σ̂, noise·|N|) per axis where a row has a measured ``noise``
    (M,) mm and a class ≥ 0; σ̂ elsewhere, and class −1 (the all-class multipliers) where the noise is not
    measured. ``sig`` (M, 3) σ̂ mm (NaN rows stay NaN), ``normals`` (M, 3) the rows' unit normals, ``surface_class``
    (M,) int (−1: none)."""
    sig = np.asarray(sig, np.float64)
    noise = np.asarray(noise, np.float64).reshape(-1)
    cls = np.asarray(surface_class).reshape(-1)
    if not (len(sig) == len(noise) == len(cls) == len(normals)):
        raise ValueError(f"effective_sigma: {len(sig)} rows of sigma, {len(normals)} normals, {len(cls)} classes, "
                         f"{len(noise)} noise scales")
    if sig.shape[1:] != (3,) or np.shape(normals)[1:] != (3,):  # the kernel reads three axes of each row
        raise ValueError(f"effective_sigma: sigma {sig.shape} and normals {np.shape(normals)} must be (M, 3)")
    out = np.empty((len(sig), 3), np.float64)
    cls_eff = np.empty(len(sig), np.int8)
    _effective(np.ascontiguousarray(sig), np.ascontiguousarray(normals), np.ascontiguousarray(cls),
               np.ascontiguousarray(noise), out, cls_eff)
    return out, cls_eff


@njit(cache=True, nogil=True, parallel=True)
def _effective(sig: np.ndarray, normals: np.ndarray, cls: np.ndarray, noise: np.ndarray, out: np.ndarray,
               cls_eff: np.ndarray) -> None:  # pragma: no cover - compiled
    """:func:`effective_sigma` in one pass over the rows (each row writes only its own: any thread count, the same
    bits as numpy's ``where(use, maximum(sig, noise·|N|), sig)``, NaN propagated as ``maximum`` does)."""
    for i in prange(sig.shape[0]):
        s = noise[i]
        has = np.isfinite(s)
        c = cls[i] if has else -1
        cls_eff[i] = c
        for a in range(3):
            v = sig[i, a]
            if has and c >= 0:
                m = s * abs(np.float64(normals[i, a]))
                if np.isnan(v) or np.isnan(m):
                    v = np.nan
                elif m > v:
                    v = m
            out[i, a] = v
