"""Measured tilt noise of an organized scan: how far each kept point's measured unit normal errs in direction, per
component (radians ≈ the error of n_x, n_y, n_z), read from the scan itself, with no model of the scanner's noise.

The grid normals (:mod:`.grid`) are window means over ``grid_window`` × ``grid_window`` cells, so two normals
``offset`` = ``grid_window`` cells apart along a grid line are fitted on disjoint windows and err independently. The
second difference of three such normals, n(j − k) − 2 n(j) + n(j + k), removes the normal's own change across the
surface (its value and its slope: a constant curvature) and leaves their errors (variance 6 τ² for independent
errors τ); the scale at a point is the mean of |second difference| / √6 over the ``WINDOW`` × ``WINDOW`` cells around
it, along the laser line and across the profiles both (at least ``MIN_SAMPLES`` of them), × √(π/2) (the mean absolute
value of a normal variable is τ·√(2/π)), per component.

Why: the along-normal block's allowance for the normal's direction error (:mod:`xmetro_ros.judge.along_normal`,
allowance model ``measured_tilt``) needs that error on each axis. Modelled from the noise along the normal and the
grid spacings (σ/h, the ``tangent_slopes`` model) it knows noise only: on the generated step's level faces within
1 mm of an edge the grid normals' window reaches across the edge, n_y errs ~10 times as much as 2 mm away, and that
model's 95 % quantile of |error| / allowance is 3-5 times its value away from the edges (the step's Y covered
90.6 % at 10/4/0.5, docs/along-normal.md). Over τ the same quantile reads 1.2-2.4 near the edges and away from them,
and on a level plate at 0.1, 0.5 and 2 ms (test/test_tilt_noise.py). Where the normal turns sharply (an edge, a
fillet) the second difference also reads the change of curvature: τ is then large, and so is the allowance (the
calibration's sharp class sets its factor).

Unorganized scans have no grid: NaN. Compiled with numba, parallel over grid rows (each point written by its own
row, in one fixed order: the same bits at any thread count).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit, prange

from ..compute import threads as _threads  # noqa: F401 - the threading layer, before any parallel kernel runs

__all__ = ["MIN_SAMPLES", "WINDOW", "grid_tilt_noise", "tilt_noise", "warm_up"]

#: Side of the square of grid cells (rows × columns) the scale is averaged over.
WINDOW = 11
#: Fewest second differences a scale is taken from (fewer: NaN, near holes and the scan's borders).
MIN_SAMPLES = 10
_SQRT6 = float(np.sqrt(6.0))
_MEAN_ABS_TO_STD = float(np.sqrt(np.pi / 2.0))


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def _second_differences(rows: np.ndarray, N: np.ndarray, k: int, out: np.ndarray,
                        cnt: np.ndarray) -> None:  # pragma: no cover - compiled
    """Per grid cell (H, W) the sum over the two grid directions of |n(−k) − 2 n + n(+k)| / √6 per component into
    ``out`` (H, W, 3), and how many directions had all three normals into ``cnt`` (H, W); ``rows`` (H, W): row of
    each cell's point, −1 where none."""
    h, w = rows.shape
    for i in prange(h):
        for j in range(w):
            a = rows[i, j]
            s0 = 0.0
            s1 = 0.0
            s2 = 0.0
            c = 0
            if a >= 0:
                if j >= k and j + k < w and rows[i, j - k] >= 0 and rows[i, j + k] >= 0:
                    b, e = rows[i, j - k], rows[i, j + k]
                    s0 += abs(np.float64(N[b, 0]) - 2.0 * np.float64(N[a, 0]) + np.float64(N[e, 0]))
                    s1 += abs(np.float64(N[b, 1]) - 2.0 * np.float64(N[a, 1]) + np.float64(N[e, 1]))
                    s2 += abs(np.float64(N[b, 2]) - 2.0 * np.float64(N[a, 2]) + np.float64(N[e, 2]))
                    c += 1
                if i >= k and i + k < h and rows[i - k, j] >= 0 and rows[i + k, j] >= 0:
                    b, e = rows[i - k, j], rows[i + k, j]
                    s0 += abs(np.float64(N[b, 0]) - 2.0 * np.float64(N[a, 0]) + np.float64(N[e, 0]))
                    s1 += abs(np.float64(N[b, 1]) - 2.0 * np.float64(N[a, 1]) + np.float64(N[e, 1]))
                    s2 += abs(np.float64(N[b, 2]) - 2.0 * np.float64(N[a, 2]) + np.float64(N[e, 2]))
                    c += 1
            out[i, j, 0] = s0 / _SQRT6
            out[i, j, 1] = s1 / _SQRT6
            out[i, j, 2] = s2 / _SQRT6
            cnt[i, j] = c


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def _window_scale(rows: np.ndarray, sd: np.ndarray, cnt: np.ndarray, half: int, min_samples: int,
                  out: np.ndarray) -> None:  # pragma: no cover - compiled
    """Mean of the second differences ``sd`` (H, W·3: each cell's three components side by side) (``cnt`` (H, W) of
    them per cell) over the (2 half + 1)² cells around each kept point, × √(π/2), into ``out`` (M, 3); NaN with fewer
    than ``min_samples``. Separable: per grid row the window's column sums first (contiguous rows added whole), then
    the sum of 2 half + 1 of them, in one order for every point."""
    h, w = rows.shape
    for i in prange(h):
        cs = np.zeros(3 * w)
        cn = np.zeros(w, np.int64)
        for ii in range(max(0, i - half), min(h, i + half + 1)):
            src = sd[ii]
            for j in range(3 * w):
                cs[j] += src[j]
            csrc = cnt[ii]
            for j in range(w):
                cn[j] += csrc[j]
        for j in range(w):
            a = rows[i, j]
            if a < 0:
                continue
            t0 = 0.0
            t1 = 0.0
            t2 = 0.0
            n = 0
            for jj in range(max(0, j - half), min(w, j + half + 1)):
                t0 += cs[3 * jj]
                t1 += cs[3 * jj + 1]
                t2 += cs[3 * jj + 2]
                n += cn[jj]
            if n >= min_samples:
                out[a, 0] = t0 / n * _MEAN_ABS_TO_STD
                out[a, 1] = t1 / n * _MEAN_ABS_TO_STD
                out[a, 2] = t2 / n * _MEAN_ABS_TO_STD
            else:
                out[a, 0] = np.nan
                out[a, 1] = np.nan
                out[a, 2] = np.nan


def grid_tilt_noise(normals: np.ndarray, index: np.ndarray, shape: tuple[int, ...], offset: int = 5,
                    window: int = WINDOW, min_samples: int = MIN_SAMPLES) -> np.ndarray:
    """(M, 3) float64 tilt noise (radians: the standard deviation of each component of the measured unit normal) of
    the M kept points with unit ``normals`` (M, 3) at flat grid cells ``index`` of ``shape`` (H, W) (H profiles × W
    points along the line); all NaN for an unorganized scan (``shape`` (N,)). ``offset``: cells between the normals
    compared (the grid normals' window side, so that their windows are disjoint); ``window``: odd side of the
    averaging square in cells."""
    m = len(index)
    if len(shape) != 2 or m == 0:
        return np.full((m, 3), np.nan)
    if window < 1 or window % 2 == 0:
        raise ValueError(f"window must be a positive odd number of cells, got {window}")
    if offset < 1:
        raise ValueError(f"offset must be at least one cell, got {offset}")
    n = np.asarray(normals)
    if n.shape != (m, 3):
        raise ValueError(f"normals must be ({m}, 3) for {m} grid cells, got {n.shape}")
    from .curvature import _grid_rows

    rows = _grid_rows(index, shape, m)
    sd = np.empty((*rows.shape, 3))
    cnt = np.empty(rows.shape, np.int64)
    _second_differences(rows, np.ascontiguousarray(n, dtype=np.float32), int(offset), sd, cnt)
    out = np.empty((m, 3))
    _window_scale(rows, sd.reshape(rows.shape[0], -1), cnt, window // 2, int(min_samples), out)
    return out


def tilt_noise(prepared: Any, offset: int = 5) -> np.ndarray:
    """(M, 3) tilt noise (radians) of a :class:`~xmetro_ros.preprocess.Prepared` scan's kept points (NaN when the
    scan is unorganized): :func:`grid_tilt_noise` on its normals, ``offset`` its grid normals' window side."""
    return grid_tilt_noise(prepared.normals, prepared.index, tuple(prepared.shape), offset=offset)


def warm_up() -> None:
    """Compile (or load from numba's cache) this module's kernels on a tiny grid."""
    g = np.arange(64, dtype=np.int64)
    n = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (64, 1))
    grid_tilt_noise(n, g, (8, 8), offset=1, window=3, min_samples=1)
