"""Unorganized path, ``"open3d"`` method (the study's reference): open3d statistical outlier removal and KD-tree
normal estimation."""

from __future__ import annotations

from typing import Any

import numpy as np

from .config import UNORGANIZED_METHODS, PreprocessError
from .knn import _knn_unorganized
from .points import _check_points, dedupe


def _o3d_cloud(points: np.ndarray) -> Any:
    import open3d as o3d

    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64)))


def remove_outliers(
    points: np.ndarray, nb_neighbors: int = 20, std_ratio: float = 2.0, *, method: str = "open3d", workers: int = 2
) -> np.ndarray:
    """Statistical outlier removal (open3d's definition) on (N, 3) finite points (mm). Returns the keep mask (N,).

    ``method="open3d"`` calls open3d; ``"knn"`` computes the same statistic from one exact kNN query (``workers``
    threads). Exact duplicates are collapsed first (they would be each other's zero-distance neighbours) and share
    the verdict of their unique point."""
    p = _check_points(points)
    if nb_neighbors < 1 or not std_ratio > 0:
        raise PreprocessError(f"nb_neighbors must be >= 1 and std_ratio > 0, got {nb_neighbors}, {std_ratio}")
    if method not in UNORGANIZED_METHODS:
        raise PreprocessError(f"method must be one of {UNORGANIZED_METHODS}, got {method!r}")
    if method == "knn":
        return _knn_unorganized(p, int(nb_neighbors), float(std_ratio), 0.0, 0, normals=False, workers=workers)[0]
    first, inverse = dedupe(p)
    keep_u = np.zeros(len(first), dtype=bool)
    if len(first) <= nb_neighbors:
        keep_u[:] = True  # too few points for the statistic: keep all
    else:
        _, idx = _o3d_cloud(p[first]).remove_statistical_outlier(nb_neighbors=int(nb_neighbors), std_ratio=std_ratio)
        keep_u[np.asarray(idx, dtype=np.int64)] = True
    return keep_u[inverse]


def normals_open3d(points: np.ndarray, *, radius_mm: float = 1.5, max_nn: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """open3d KD-tree normal estimation (hybrid ``radius_mm`` / ``max_nn``) of finite points (N, 3) mm, duplicates
    collapsed first. Returns (normals (N, 3) float32, sign arbitrary; quality (N,) float32 = 1 − nearest-neighbour
    distance / radius, clipped to [0, 1])."""
    import open3d as o3d

    first, inverse = dedupe(points)
    pu = points[first]
    if len(pu) < 3:
        return np.zeros((len(points), 3), np.float32), np.zeros(len(points), np.float32)
    pc = _o3d_cloud(pu)
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=float(radius_mm), max_nn=int(max_nn)))
    nu = np.asarray(pc.normals, dtype=np.float32)
    # Quality: 1 − (nearest-neighbour distance / radius), clipped: 0 for lone points (open3d gives them an
    # arbitrary normal), low in sparse regions. A neighbour-count query would double the cost of this path.
    dnn = np.asarray(pc.compute_nearest_neighbor_distance(), dtype=np.float32)
    qu = np.clip(1.0 - dnn / np.float32(radius_mm), 0.0, 1.0).astype(np.float32)
    return nu[inverse], qu[inverse]


