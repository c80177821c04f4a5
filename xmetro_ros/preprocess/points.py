"""Helpers shared by the pre-processing paths: point checks, orientation of normals, exact duplicates."""

from __future__ import annotations

import numpy as np
from numba import njit

from .config import PreprocessError


def _check_points(points: np.ndarray, allow_nan: bool = False) -> np.ndarray:
    p = np.asarray(points)
    if p.ndim != 2 or p.shape[1] != 3:
        raise PreprocessError(f"points must have shape (N, 3), got {p.shape}")
    if len(p) == 0:
        raise PreprocessError("empty point cloud")
    if not allow_nan and not np.all(np.isfinite(p)):
        raise PreprocessError(f"{int((~np.isfinite(p).all(axis=1)).sum())} points are not finite (NaN/inf)")
    return p


def _orient(normals: np.ndarray, points: np.ndarray, toward: np.ndarray | None) -> np.ndarray:
    """Flip normals in place to have a positive dot with ``toward`` ((N,3) or (3,)); default: away from centroid."""
    if toward is None:
        ref = points - points.mean(axis=0)
    else:
        ref = np.asarray(toward, dtype=normals.dtype)
        if ref.shape not in ((3,), normals.shape):
            raise PreprocessError(f"toward must have shape (3,) or {normals.shape}, got {ref.shape}")
    if ref.ndim == 1:  # column ops, not a BLAS gemv (threaded BLAS stalls on a busy machine)
        r = ref.astype(normals.dtype)
        d = normals[:, 0] * r[0] + normals[:, 1] * r[1] + normals[:, 2] * r[2]
    else:
        d = np.einsum("ij,ij->i", normals, ref.astype(normals.dtype, copy=False))
    # multiply by ±1 rather than a boolean-mask scatter: grid normals often all need flipping
    np.multiply(normals, np.where(d < 0, normals.dtype.type(-1), normals.dtype.type(1))[:, None], out=normals)
    return normals


#: Multipliers of the row hash of :func:`dedupe` and :func:`has_duplicates` (x, y, z bits), one per column.
_ROW_HASH = (np.uint64(0x9E3779B97F4A7C15), np.uint64(0xC2B2AE3D27D4EB4F), np.uint64(0x165667B19E3779F9))


@njit(cache=True, nogil=True)
def _any_equal_rows(bits: np.ndarray) -> bool:
    """Whether two rows of ``bits`` (N, 3) uint64 are equal: one pass through an open-addressing table of row
    numbers keyed on a hash of the row (~2 ms for 180k rows; sorting them, as :func:`dedupe` must, is ~10× that)."""
    n = bits.shape[0]
    size = 1
    while size < 2 * n:
        size *= 2
    mask = np.uint64(size - 1)
    table = np.full(size, -1, np.int64)
    for i in range(n):
        h = (bits[i, 0] * _ROW_HASH[0]) ^ (bits[i, 1] * _ROW_HASH[1]) ^ (bits[i, 2] * _ROW_HASH[2])
        s = (h >> np.uint64(20)) & mask
        while table[s] >= 0:
            j = table[s]
            if bits[j, 0] == bits[i, 0] and bits[j, 1] == bits[i, 1] and bits[j, 2] == bits[i, 2]:
                return True
            s = (s + np.uint64(1)) & mask
        table[s] = i
    return False


def has_duplicates(points: np.ndarray) -> bool:
    """Whether any two points (N, 3) are exactly equal (−0.0 equal to +0.0, as :func:`dedupe` counts them): the
    check before :func:`dedupe`, which a scan of distinct points (every scan of a line scanner) need not pay."""
    p = np.ascontiguousarray(points, dtype=np.float64) + 0.0  # -0.0 → +0.0 so equal coordinates have equal bits
    return bool(_any_equal_rows(p.view(np.uint64).reshape(-1, 3)))


def dedupe(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact duplicate points removed: (unique_index (U,), inverse (N,)) with points[unique_index][inverse] ==
    points. Hashes the coordinate bits (one 1-D sort, ~10× faster than ``np.unique(axis=0)``), verified exactly."""
    p = np.ascontiguousarray(points, dtype=np.float64)
    p = p + 0.0  # -0.0 → +0.0 so equal coordinates have equal bits
    bits = p.view(np.uint64).reshape(-1, 3)
    h = bits[:, 0] * _ROW_HASH[0] ^ bits[:, 1] * _ROW_HASH[1] ^ bits[:, 2] * _ROW_HASH[2]
    _, first, inverse = np.unique(h, return_index=True, return_inverse=True)
    if not np.array_equal(p[first[inverse]], p):  # hash collision (never seen): exact but slower path
        _, first, inverse = np.unique(p, axis=0, return_index=True, return_inverse=True)
    return first, inverse.reshape(-1)
