"""Compiled (numba) per-point geometry: of scans whose every profile has its own head pose
(:func:`xmetro_ros.scan.geometry.point_geometry_posed`): one pass over the points, float64, no GIL held — the numpy
version gathered an (N, 3, 3) rotation per point and took a third of a 400k-point stream scan's judging time; and of
a scan from one pose (:func:`xmetro_ros.scan.geometry.point_geometry`), split over the judge's threads, in the
float operations and types of the numpy expressions it replaced (element by element, the same bits; tested against
them in test/test_geometry_kernels.py).

Compile cost: ``cache=True`` keeps the machine code in ``__pycache__`` (or ``NUMBA_CACHE_DIR``) after the first call.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit, prange

from ..compute import threads as _threads  # noqa: F401 - the threading layer, before any parallel kernel runs

__all__ = ["posed_geometry", "single_pose_geometry_rotated", "single_pose_geometry_straight"]


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def posed_geometry(points: np.ndarray, pose_index: np.ndarray, positions: np.ndarray, rotations: np.ndarray,
                   camera: np.ndarray, s_origin: np.ndarray, s_axis: np.ndarray, out: np.ndarray, z_out: np.ndarray,
                   s_out: np.ndarray) -> None:  # pragma: no cover - compiled
    """Fill ``out`` (8, N): L (3), V (3) in the scan frame, source distance, head x; ``z_out`` head z; ``s_out``
    the position along ``s_axis`` from ``s_origin`` (mm). Point n is seen from pose ``pose_index[n]``: head
    coordinates p_h = R^T (p − o); the source on the point's head-Y line; the camera at ``camera`` from it."""
    cx, cy, cz = camera[0], camera[1], camera[2]
    for n in prange(points.shape[0]):
        k = pose_index[n]
        d0 = points[n, 0] - positions[k, 0]
        d1 = points[n, 1] - positions[k, 1]
        d2 = points[n, 2] - positions[k, 2]
        x = rotations[k, 0, 0] * d0 + rotations[k, 1, 0] * d1 + rotations[k, 2, 0] * d2
        z = rotations[k, 0, 2] * d0 + rotations[k, 1, 2] * d1 + rotations[k, 2, 2] * d2
        dist = math.sqrt(x * x + z * z)
        inv_s = 1.0 / dist if dist > 0 else 0.0
        tx, tz = cx - x, cz - z
        dcam = math.sqrt(tx * tx + tz * tz + cy * cy)
        inv_c = 1.0 / dcam if dcam > 0 else 0.0
        lx, lz = -x * inv_s, -z * inv_s
        vx, vy, vz = tx * inv_c, cy * inv_c, tz * inv_c
        for j in range(3):  # head frame → scan frame
            out[j, n] = rotations[k, j, 0] * lx + rotations[k, j, 2] * lz
            out[3 + j, n] = rotations[k, j, 0] * vx + rotations[k, j, 1] * vy + rotations[k, j, 2] * vz
        out[6, n] = dist
        out[7, n] = x
        z_out[n] = z
        s_out[n] = ((points[n, 0] - s_origin[0]) * s_axis[0] + (points[n, 1] - s_origin[1]) * s_axis[1]
                    + (points[n, 2] - s_origin[2]) * s_axis[2])


@njit(cache=True, nogil=True, error_model="numpy")
def _source_and_camera(x: Any, z: Any, one: Any, zero: Any, cx: Any, cz: Any, cy2: Any, common: bool
                       ) -> tuple[Any, Any, Any, Any, Any]:  # pragma: no cover - compiled
    """From head coordinates x, z of a point (in the float type of ``one``): (source distance, its inverse (0 at
    the source), the camera offsets tx, tz, the inverse camera distance); ``cy2`` = cy², ``common``: cx = cz = 0."""
    xz2 = x * x + z * z
    dist = np.sqrt(xz2)
    inv_s = one / dist if dist > zero else zero
    if common:
        tx = -x
        tz = -z
        dcam = np.sqrt(xz2 + cy2)
    else:
        tx = cx - x
        tz = cz - z
        dcam = np.sqrt(tx * tx + tz * tz + cy2)
    inv_c = one / dcam if dcam > zero else zero
    return dist, inv_s, tx, tz, inv_c


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def single_pose_geometry_straight(points: np.ndarray, position: np.ndarray, one: Any, zero: Any, cxf: Any, cyf: Any,
                                  czf: Any, cy2: Any, common: bool, L: np.ndarray, V: np.ndarray, dist_out: np.ndarray,
                                  standoff: np.ndarray, u: np.ndarray, s: np.ndarray) -> None:  # pragma: no cover
    """The geometry from a pose whose rotation is the identity, in the outputs' float type (float32 on the hot
    path): ``one``, ``zero``, the camera ``cxf, cyf, czf`` and ``cy2`` = cy² are scalars of that type; ``common``:
    the camera at the laser's height (cx = cz = 0)."""
    p0, p1, p2 = position[0], position[1], position[2]
    for i in prange(points.shape[0]):
        u[i] = points[i, 0] - p0  # stored in the output type: numpy's cast of the float64 difference
        s[i] = points[i, 1] - p1
        standoff[i] = points[i, 2] - p2
        x = u[i]
        z = standoff[i]
        dist_out[i], inv_s, tx, tz, inv_c = _source_and_camera(x, z, one, zero, cxf, czf, cy2, common)
        L[i, 0] = -x * inv_s
        L[i, 1] = zero
        L[i, 2] = -z * inv_s
        V[i, 0] = tx * inv_c
        V[i, 1] = cyf * inv_c
        V[i, 2] = tz * inv_c
        standoff[i] = -z


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def single_pose_geometry_rotated(points: np.ndarray, position: np.ndarray, r: np.ndarray, round32: bool, cx: float,
                                 cy: float, cz: float, common: bool, L: np.ndarray, V: np.ndarray, dist_out: np.ndarray,
                                 standoff: np.ndarray, u: np.ndarray, s: np.ndarray) -> None:  # pragma: no cover
    """The geometry from a turned pose (rotation ``r``), in float64 as numpy computes it (a float64 rotation times
    the points' offsets); ``round32``: the offsets are first rounded to float32 (the float32 hot path's cast)."""
    p0, p1, p2 = position[0], position[1], position[2]
    cy2 = cy * cy
    one, zero = 1.0, 0.0
    for i in prange(points.shape[0]):
        d0 = points[i, 0] - p0
        d1 = points[i, 1] - p1
        d2 = points[i, 2] - p2
        if round32:
            d0 = np.float64(np.float32(d0))
            d1 = np.float64(np.float32(d1))
            d2 = np.float64(np.float32(d2))
        x = r[0, 0] * d0 + r[1, 0] * d1 + r[2, 0] * d2
        y = r[0, 1] * d0 + r[1, 1] * d1 + r[2, 1] * d2
        z = r[0, 2] * d0 + r[1, 2] * d1 + r[2, 2] * d2
        dist, inv_s, tx, tz, inv_c = _source_and_camera(x, z, one, zero, cx, cz, cy2, common)
        lh0 = -x * inv_s
        lh2 = -z * inv_s
        vh0 = tx * inv_c
        vh1 = cy * inv_c
        vh2 = tz * inv_c
        for k in range(3):
            L[i, k] = r[k, 0] * lh0 + r[k, 2] * lh2
            V[i, k] = r[k, 0] * vh0 + r[k, 1] * vh1 + r[k, 2] * vh2
        dist_out[i] = dist
        standoff[i] = -z
        u[i] = x
        s[i] = y
