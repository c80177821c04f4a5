"""Unorganized path, ``"knn"`` method: ONE k-nearest-neighbour query (a compiled grid search) for both the statistical
outlier removal (open3d's definition) and the covariance normals (closed-form 3×3 eigen-solver)."""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..compute import threads as _threads  # the threading layer, before any parallel kernel runs
from .knn_grid import knn_grid
from .points import dedupe, has_duplicates


def _knn(points: np.ndarray, k: int, workers: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact k nearest neighbours of every point among the (distinct, finite) points (U, 3), the point itself
    included first (distance 0), as open3d's KNN search does: the compiled grid search of :mod:`.knn_grid` on
    ``workers`` threads. Returns (dist (U, k) float64 mm ascending, idx (U, k) int64 into points, query (U,) int64):
    row r holds the neighbours of ``points[query[r]]``. The rows come in grid-cell order (neighbouring queries read
    the same cells) and callers index by ``query`` instead of paying to scatter (U, k) arrays back. The same
    neighbours and distance bits as scipy's ``cKDTree`` (up to the order of equal distances; test_knn_grid.py), in
    0.41-0.43× its time on a 178k-point scan at 1 and 2 threads (docs/node.md)."""
    before = _threads.budget()
    _threads.use_threads(max(1, int(workers)))
    try:
        return knn_grid(points, k)
    finally:
        _threads.use_threads(before)


def _sor_keep(dist: np.ndarray, nb_neighbors: int, std_ratio: float) -> np.ndarray:
    """open3d's statistical outlier removal from sorted kNN distances (U, >= nb_neighbors), self included: mean
    distance to the nb_neighbors nearest; keep 0 < mean < global mean + std_ratio × std (Bessel), with open3d's
    bookkeeping (zero means are left out of the sums but counted in the divisor)."""
    avg = dist[:, :nb_neighbors].mean(axis=1)
    n = len(avg)
    pos = avg > 0
    mean = float(avg[pos].sum()) / n
    std = float(np.sqrt(((avg[pos] - mean) ** 2).sum() / max(n - 1, 1)))
    return pos & (avg < mean + std_ratio * std)


def _smallest_eigvec_sym3(a00, a01, a02, a11, a12, a22):
    """Closed-form eigen-decomposition of N symmetric 3×3 matrices given as columns (N,) float64 (trigonometric
    method, then the eigenvector as the largest cross product of two rows of A − λ0 I; A positive semi-definite,
    e.g. a covariance). Returns (normal (N, 3)
    float64 unit, NaN where undefined; λ0, λ1, λ2 ascending (N,))."""
    scale = a00 + a11 + a22  # a covariance is positive semi-definite: its trace bounds every element
    s = np.where(scale > 0, scale, 1.0)
    a00, a01, a02, a11, a12, a22 = (a / s for a in (a00, a01, a02, a11, a12, a22))
    q = (a00 + a11 + a22) / 3
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p2 = (b00 * b00 + b11 * b11 + b22 * b22 + 2 * (a01 * a01 + a02 * a02 + a12 * a12)) / 6
    p = np.sqrt(p2)
    det = b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.clip(np.where(p > 0, det / (2 * p * p2), 0.0), -1.0, 1.0)
    phi = np.arccos(r) / 3
    l2 = q + 2 * p * np.cos(phi)
    l0 = q + 2 * p * np.cos(phi + 2 * np.pi / 3)
    l1 = 3 * q - l2 - l0
    r0 = (a00 - l0, a01, a02)
    r1 = (a01, a11 - l0, a12)
    r2 = (a02, a12, a22 - l0)

    def cross(u, v):
        return (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])

    c0, c1, c2 = cross(r0, r1), cross(r0, r2), cross(r1, r2)
    n0, n1, n2 = (c[0] * c[0] + c[1] * c[1] + c[2] * c[2] for c in (c0, c1, c2))
    pick0 = (n0 >= n1) & (n0 >= n2)
    pick1 = ~pick0 & (n1 >= n2)
    nn = np.sqrt(np.where(pick0, n0, np.where(pick1, n1, n2)))
    with np.errstate(invalid="ignore", divide="ignore"):
        inv = 1.0 / np.where(nn > 1e-30, nn, np.nan)
    normal = np.empty((len(a00), 3))
    for j in range(3):
        normal[:, j] = np.where(pick0, c0[j], np.where(pick1, c1[j], c2[j])) * inv
    return normal, l0 * s, l1 * s, l2 * s


def _knn_normals_numpy(
    points: np.ndarray, rows: np.ndarray, dist: np.ndarray, idx: np.ndarray, allowed: np.ndarray, radius_mm: float
) -> tuple[np.ndarray, np.ndarray]:
    """The numpy reference of the compiled :func:`_knn_normals` (test_preprocess.py compares them). Normals (R, 3)
    float32 (NaN where undefined) and planarity quality (R,) float32 of ``points[rows]`` (points (U, 3) mm) from their
    kNN (dist, idx (R, k) into points), using only the neighbours ``allowed`` (e.g. not
    outliers, (U,) bool) and within
    ``radius_mm`` (open3d's hybrid search). Covariance of the neighbour offsets from the query point in float32,
    column-wise (no small BLAS matmuls); eigenvectors in closed form. Quality = 1 − λ0/λ1 (eigenvalues ascending):
    1 for a flat, two-dimensional neighbourhood, 0 for an isotropic (noise) or collinear one or < 3 neighbours."""
    w = allowed[idx]
    w &= dist <= radius_mm
    cnt = np.count_nonzero(w, axis=1).astype(np.float64)
    # unused neighbours point at the query point itself: their offset is 0 and adds nothing to the sums below
    idx = np.where(w, idx, rows[:, None])
    pc = points - points.mean(axis=0)
    g = []
    for j in range(3):  # offsets of the neighbours from the point (mm, float32)
        c = pc[:, j].astype(np.float32)
        gj = c[idx]
        gj -= c[rows][:, None]
        g.append(gj)
    inv = np.divide(1.0, cnt, out=np.zeros_like(cnt), where=cnt > 0)
    m = [np.einsum("ij->i", g[j]) * inv for j in range(3)]  # float32 sums of small offsets, float64 from here

    def cov(a: int, b: int) -> np.ndarray:
        return np.einsum("ij,ij->i", g[a], g[b]).astype(np.float64) * inv - m[a] * m[b]

    normal, l0, l1, l2 = _smallest_eigvec_sym3(cov(0, 0), cov(0, 1), cov(0, 2), cov(1, 1), cov(1, 2), cov(2, 2))
    ok = (cnt >= 3) & (l1 > 1e-12 * np.maximum(l2, 1e-300)) & np.isfinite(normal).all(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        quality = np.where(ok, np.clip(1.0 - np.maximum(l0, 0) / l1, 0.0, 1.0), 0.0).astype(np.float32)
    normal[~ok] = np.nan
    return normal.astype(np.float32), quality


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _smallest_eigvec_one(a00: float, a01: float, a02: float, a11: float, a12: float, a22: float
                         ) -> tuple[float, float, float, float, float, float, float]:
    """:func:`_smallest_eigvec_sym3` for one matrix, the same formulas (the compiled path's copy of the numpy
    reference): (un-normalised eigenvector v0, v1, v2, its norm, λ0, λ1, λ2 ascending)."""
    scale = a00 + a11 + a22
    sc = scale if scale > 0 else 1.0
    a00, a01, a02, a11, a12, a22 = a00 / sc, a01 / sc, a02 / sc, a11 / sc, a12 / sc, a22 / sc
    qq = (a00 + a11 + a22) / 3
    b00, b11, b22 = a00 - qq, a11 - qq, a22 - qq
    p2 = (b00 * b00 + b11 * b11 + b22 * b22 + 2 * (a01 * a01 + a02 * a02 + a12 * a12)) / 6
    p = np.sqrt(p2)
    det = b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02)
    rr = det / (2 * p * p2) if p > 0 else 0.0
    rr = min(1.0, max(-1.0, rr))
    phi = np.arccos(rr) / 3
    l2 = qq + 2 * p * np.cos(phi)
    l0 = qq + 2 * p * np.cos(phi + 2 * np.pi / 3)
    l1 = 3 * qq - l2 - l0
    x0, x1, x2 = a00 - l0, a01, a02
    y0, y1, y2 = a01, a11 - l0, a12
    z0, z1, z2 = a02, a12, a22 - l0
    c00, c01, c02 = x1 * y2 - x2 * y1, x2 * y0 - x0 * y2, x0 * y1 - x1 * y0
    c10, c11, c12 = x1 * z2 - x2 * z1, x2 * z0 - x0 * z2, x0 * z1 - x1 * z0
    c20, c21, c22 = y1 * z2 - y2 * z1, y2 * z0 - y0 * z2, y0 * z1 - y1 * z0
    n0 = c00 * c00 + c01 * c01 + c02 * c02
    n1 = c10 * c10 + c11 * c11 + c12 * c12
    n2 = c20 * c20 + c21 * c21 + c22 * c22
    if n0 >= n1 and n0 >= n2:
        v0, v1, v2, nn = c00, c01, c02, n0
    elif n1 >= n2:
        v0, v1, v2, nn = c10, c11, c12, n1
    else:
        v0, v1, v2, nn = c20, c21, c22, n2
    return v0, v1, v2, np.sqrt(nn), l0 * sc, l1 * sc, l2 * sc


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def _knn_normals_kernel(c: np.ndarray, rows: np.ndarray, dist: np.ndarray, idx: np.ndarray, allowed: np.ndarray,
                        radius_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Compiled :func:`_knn_normals_numpy`: the same rules and formulas row by row (float32 offsets from the
    centred coordinates ``c`` (U, 3) float32, float64 moments, the closed-form eigenvector), without the (R, k)
    temporaries. Sums run in another order than numpy's einsum: normals agree to ~1e-7 (test_preprocess.py)."""
    r_n, k = idx.shape
    normals = np.full((r_n, 3), np.nan, np.float32)
    quality = np.zeros(r_n, np.float32)
    for r in prange(r_n):  # each row its own normal: the same bits at any thread count
        q = rows[r]
        s0 = s1 = s2 = 0.0
        s00 = s01 = s02 = s11 = s12 = s22 = 0.0
        cnt = 0
        for j in range(k):
            i = idx[r, j]
            if not (allowed[i] and dist[r, j] <= radius_mm):
                continue
            g0 = np.float32(c[i, 0] - c[q, 0])
            g1 = np.float32(c[i, 1] - c[q, 1])
            g2 = np.float32(c[i, 2] - c[q, 2])
            s0 += float(g0)
            s1 += float(g1)
            s2 += float(g2)
            s00 += float(np.float32(g0 * g0))  # float32 products, as numpy's float32 einsum
            s01 += float(np.float32(g0 * g1))
            s02 += float(np.float32(g0 * g2))
            s11 += float(np.float32(g1 * g1))
            s12 += float(np.float32(g1 * g2))
            s22 += float(np.float32(g2 * g2))
            cnt += 1
        if cnt < 3:
            continue
        inv = 1.0 / cnt
        m0, m1, m2 = s0 * inv, s1 * inv, s2 * inv
        a00, a01, a02 = s00 * inv - m0 * m0, s01 * inv - m0 * m1, s02 * inv - m0 * m2
        a11, a12, a22 = s11 * inv - m1 * m1, s12 * inv - m1 * m2, s22 * inv - m2 * m2
        v0, v1, v2, nn, l0, l1, l2 = _smallest_eigvec_one(a00, a01, a02, a11, a12, a22)
        if not (nn > 1e-30 and l1 > 1e-12 * max(l2, 1e-300)):
            continue
        normals[r, 0], normals[r, 1], normals[r, 2] = v0 / nn, v1 / nn, v2 / nn
        quality[r] = min(1.0, max(0.0, 1.0 - max(l0, 0.0) / l1))
    return normals, quality


def _knn_normals(
    points: np.ndarray, rows: np.ndarray, dist: np.ndarray, idx: np.ndarray, allowed: np.ndarray, radius_mm: float
) -> tuple[np.ndarray, np.ndarray]:
    """As :func:`_knn_normals_numpy`, compiled (numba): ~10× faster on a 180k cloud (no (R, k) temporaries)."""
    pc = (points - points.mean(axis=0)).astype(np.float32)
    return _knn_normals_kernel(pc, np.ascontiguousarray(rows, np.int64), np.ascontiguousarray(dist, np.float64),
                               np.ascontiguousarray(idx, np.int64), np.ascontiguousarray(allowed, np.bool_),
                               float(radius_mm))


def _knn_unorganized(
    points: np.ndarray, nb_neighbors: int, std_ratio: float, radius_mm: float, normal_neighbors: int, *,
    remove: bool = True, outliers: bool = True, normals: bool = True, workers: int = 2,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """The knn method on finite points (N, 3) mm: dedupe, one kNN query with k = max(nb_neighbors,
    normal_neighbors), SOR keep mask, normals among the kept points (all points when ``remove`` is False). Returns
    (keep (N,) bool, normals (N, 3) float32 | None, quality (N,) float32 | None); duplicates share their point's
    verdict and normal; the normals of removed points (remove=True) are NaN."""
    inverse: np.ndarray | slice
    if not has_duplicates(points):  # keep the input order and skip dedupe's sort and the gathers back
        pu, inverse = np.ascontiguousarray(points, dtype=np.float64), slice(None)
    else:
        first, inverse = dedupe(points)
        pu = np.ascontiguousarray(points[first], dtype=np.float64)
    u = len(pu)
    keep_u = np.ones(u, dtype=bool)
    k = min(u, max(nb_neighbors if outliers else 1, normal_neighbors if normals else 1))
    if u >= 2:
        dist, idx, query = _knn(pu, k, workers)
    else:
        dist, idx, query = np.zeros((u, 1)), np.zeros((u, 1), np.int64), np.arange(u)
    if outliers and u > nb_neighbors:  # fewer points than the statistic needs: keep all (as before)
        keep_u[query] = _sor_keep(dist, nb_neighbors, std_ratio)
    if not normals:
        return keep_u[inverse], None, None
    allowed = keep_u if remove else np.ones(u, dtype=bool)
    kn = min(k, normal_neighbors)
    nu = np.full((u, 3), np.nan, dtype=np.float32)
    qu = np.zeros(u, dtype=np.float32)
    if u >= 3:
        # all query rows (the few outliers too): cheaper than copying the (U, k) arrays without them
        nu[query], qu[query] = _knn_normals(pu, query, dist[:, :kn], idx[:, :kn], allowed, radius_mm)
        if remove:
            nu[~allowed] = np.nan  # removed points get no normal
            qu[~allowed] = 0
    return keep_u[inverse], nu[inverse], qu[inverse]




def normals_knn(
    points: np.ndarray, *, radius_mm: float = 1.5, max_nn: int = 30, workers: int = 2
) -> tuple[np.ndarray, np.ndarray]:
    """Normals of finite points (N, 3) mm from the covariance of their ``max_nn`` nearest neighbours within
    ``radius_mm`` (one kNN query on ``workers`` threads; smallest eigenvector in closed form). Returns
    (normals (N, 3) float32, NaN where undefined, sign arbitrary; quality = planarity 1 − λ0/λ1 (N,) float32)."""
    _, normals, quality = _knn_unorganized(points, 0, 0.0, float(radius_mm), int(max_nn), outliers=False,
                                           workers=workers)
    assert normals is not None and quality is not None  # asked for (normals=True is the default)
    return normals, quality


