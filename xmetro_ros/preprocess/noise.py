"""Measured noise of an organized scan: the spread of each kept point's depth along its normal (mm), read from the
scan itself, with no model and no assumption about the scanner.

Along a laser line the points of a smooth surface lie on a smooth curve; the second difference of three
neighbouring points, p(j−1) − 2 p(j) + p(j+1), projected on the normal, removes the curve's position and slope
and leaves its white noise (variance 6 σ² for independent depth noise σ) plus the curvature's h²κ (~2 µm at
1/6 mm spacing on a 12 mm radius: small against the noise it measures). The scale at a point is the mean of
|second difference| / √6 over the ``WINDOW`` × ``WINDOW`` grid cells around it (at least ``MIN_SAMPLES`` of them),
× √(π/2) (the mean absolute value of a normal variable is σ·√(2/π)).

Why: the PointNet's σ̂ of a point depends on the whole scan it sits in (its sets are random samples of the scan),
so on a part it never saw σ̂ can be off by a factor: on the generated bowl's flat top at 6/3/0.1, σ̂_z is 13 µm
where a calibration plate at the same incidence, view and stand-off gets 17-19 µm, the same true noise (16.4 µm)
in both. The measured scale reads 0.95-0.96 of the simulator's true noise on both and on two more surfaces
(``tools/sigma_context.py``; test/test_noise.py holds it to 0.8-1.1). What it misses
(noise correlated over more than a cell, e.g. speckle; lateral noise along the line) the conformal multiplier and
σ̂ still carry: U uses the larger of the two (:func:`xmetro_ros.judge.measured_noise.effective_sigma`).

Unorganized scans have no grid: NaN (their U uses σ̂ alone). Compiled with numba, parallel over grid rows (each
point written by its own row, in one fixed order: the same bits at any thread count).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit, prange

from ..compute import threads as _threads  # noqa: F401 - the threading layer, before any parallel kernel runs

__all__ = ["MIN_SAMPLES", "WINDOW", "grid_noise_scale", "noise_scale", "warm_up"]

#: Side of the square of grid cells (rows × columns) the scale is averaged over: 1.2 × 2.3 mm at 6/3 points/mm,
#: 0.5 × 1.4 mm at 15/5.
WINDOW = 7
#: Fewest second differences a scale is taken from (fewer: NaN, at holes and along the scan's borders).
MIN_SAMPLES = 10
_SQRT6 = float(np.sqrt(6.0))
_MEAN_ABS_TO_STD = float(np.sqrt(np.pi / 2.0))


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def _second_differences(rows: np.ndarray, P: np.ndarray, N: np.ndarray, out: np.ndarray) -> None:
    """|(p(j−1) − 2 p(j) + p(j+1)) · n(j)| / √6 at every grid cell whose point and both line neighbours are kept
    (NaN elsewhere), into the grid ``out`` (H, W); ``rows`` (H, W): row of each cell's point, −1 where none."""
    h, w = rows.shape
    for i in prange(h):
        out[i, 0] = np.nan
        out[i, w - 1] = np.nan
        for j in range(1, w - 1):
            a, b, c = rows[i, j], rows[i, j - 1], rows[i, j + 1]
            if a < 0 or b < 0 or c < 0:
                out[i, j] = np.nan
                continue
            d = 0.0
            for k in range(3):
                d += (P[b, k] - 2.0 * P[a, k] + P[c, k]) * np.float64(N[a, k])
            out[i, j] = abs(d) / _SQRT6


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def _window_scale(rows: np.ndarray, sd: np.ndarray, half: int, min_samples: int, out: np.ndarray) -> None:
    """Mean of the finite grid values ``sd`` (H, W) over the (2 half + 1)² cells around each kept point, ×
    √(π/2), into ``out`` (M,); NaN with fewer than ``min_samples`` of them. Separable: per grid row, the window's
    column sums first, then the sum of 2 half + 1 of them (14 reads a point instead of 49 at 7 × 7, all of them
    contiguous), in one order for every point."""
    h, w = rows.shape
    for i in prange(h):
        cs = np.zeros(w)
        cn = np.zeros(w, np.int64)
        for ii in range(max(0, i - half), min(h, i + half + 1)):
            for j in range(w):
                v = sd[ii, j]
                if v == v:  # finite (sd is never inf)
                    cs[j] += v
                    cn[j] += 1
        for j in range(w):
            a = rows[i, j]
            if a < 0:
                continue
            acc = 0.0
            cnt = 0
            for jj in range(max(0, j - half), min(w, j + half + 1)):
                acc += cs[jj]
                cnt += cn[jj]
            out[a] = acc / cnt * _MEAN_ABS_TO_STD if cnt >= min_samples else np.nan


def grid_noise_scale(points: np.ndarray, normals: np.ndarray, index: np.ndarray, shape: tuple[int, ...],
                     window: int = WINDOW, min_samples: int = MIN_SAMPLES) -> np.ndarray:
    """(M,) float64 noise scale (mm, the standard deviation of the depth along the normal) of the M kept points
    ``points`` / unit ``normals`` (M, 3) at flat grid cells ``index`` of ``shape`` (H, W) (H profiles × W points
    along the line); all NaN for an unorganized scan (``shape`` (N,)). ``window``: odd side of the averaging square
    in cells."""
    m = len(index)
    if len(shape) != 2 or m == 0:
        return np.full(m, np.nan)
    if window < 1 or window % 2 == 0:
        raise ValueError(f"window must be a positive odd number of cells, got {window}")
    from .curvature import _grid_rows

    rows = _grid_rows(index, shape, m)
    if rows.shape[1] < 3:  # no point has both line neighbours
        return np.full(m, np.nan)
    sd = np.empty(rows.shape)
    _second_differences(rows, np.ascontiguousarray(points, dtype=np.float64),
                        np.ascontiguousarray(normals, dtype=np.float32), sd)
    out = np.empty(m)
    _window_scale(rows, sd, window // 2, int(min_samples), out)
    return out


def noise_scale(prepared: Any) -> np.ndarray:
    """(M,) noise scale (mm, along the normal) of a :class:`~xmetro_ros.preprocess.Prepared` scan's kept points
    (NaN when the scan is unorganized): :func:`grid_noise_scale`."""
    return grid_noise_scale(prepared.points, prepared.normals, prepared.index, tuple(prepared.shape))


def warm_up() -> None:
    """Compile (or load from numba's cache) this module's kernels on a tiny grid."""
    g = np.arange(64, dtype=np.int64)
    p = np.column_stack([g % 8, g // 8, np.zeros(64)]).astype(np.float64)
    n = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (64, 1))
    grid_noise_scale(p, n, g, (8, 8), window=3, min_samples=1)
