"""``estimate_normals``: one entry point dispatching to the grid, knn or open3d normal estimation, then
orienting."""

from __future__ import annotations

import numpy as np

from .config import UNORGANIZED_METHODS, PreprocessError
from .grid import normals_grid
from .knn import normals_knn
from .open3d_ref import normals_open3d
from .points import _check_points, _orient


def estimate_normals(
    points: np.ndarray,
    *,
    grid_shape: tuple[int, int] | None = None,
    grid_index: np.ndarray | None = None,
    radius_mm: float = 1.5,
    max_nn: int = 30,
    toward: np.ndarray | None = None,
    grid_window: int = 5,
    method: str = "open3d",
    workers: int = 2,
    grid_backend: str = "numba",
) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (N, 3) float32 and a quality (N,) float32 in [0, 1] for finite points (N, 3), mm: a dispatcher.

    With ``grid_shape=(H, W)`` and ``grid_index`` (flat index of each point into the H×W grid):
    :func:`normals_grid` (``grid_window`` cells, ``grid_backend``); otherwise ``method="open3d"``:
    :func:`normals_open3d` (hybrid ``radius_mm`` / ``max_nn``), or ``"knn"``: :func:`normals_knn` (``workers``
    threads). Normals are oriented to have a positive dot with ``toward`` ((N,3) or (3,)), or away from the
    centroid. Points without a usable neighbourhood get quality 0 and the orientation reference as normal."""
    p = _check_points(points)
    if grid_shape is not None:
        if grid_index is None:
            raise PreprocessError("grid_shape needs grid_index (flat index of each point into the grid)")
        normals, quality = normals_grid(p, grid_shape, grid_index, grid_window=grid_window, backend=grid_backend)
    else:
        if not radius_mm > 0 or max_nn < 3:
            raise PreprocessError(f"radius_mm must be > 0 and max_nn >= 3, got {radius_mm}, {max_nn}")
        if method == "knn":
            normals, quality = normals_knn(p, radius_mm=radius_mm, max_nn=max_nn, workers=workers)
        elif method == "open3d":
            normals, quality = normals_open3d(p, radius_mm=radius_mm, max_nn=max_nn)
        else:
            raise PreprocessError(f"method must be one of {UNORGANIZED_METHODS}, got {method!r}")
    normals = np.ascontiguousarray(normals, dtype=np.float32)
    bad = ~np.isfinite(normals).all(axis=1) | (np.einsum("ij,ij->i", normals, normals) < 0.25)
    _orient(normals, p, toward)
    if bad.any():
        if toward is not None and np.ndim(toward) == 2:
            ref = np.asarray(toward, np.float32)[bad]
        elif toward is not None:
            ref = np.broadcast_to(np.asarray(toward, np.float32), (int(bad.sum()), 3))
        else:
            ref = (p[bad] - p.mean(axis=0)).astype(np.float32)
        nr = np.linalg.norm(ref, axis=1, keepdims=True)
        normals[bad] = np.where(nr > 0, ref / np.where(nr > 0, nr, 1), np.array([0, 0, 1], dtype=np.float32))
        quality = quality.copy()
        quality[bad] = 0.0
    return normals, np.asarray(quality, dtype=np.float32)


