"""Compiled (numba) organized-grid pre-processing: the rules of :mod:`xmetro_ros.preprocess`'s numpy grid path
(``_planes``, ``_grid_outliers_planes``, ``_grid_normals_planes``, the gather of the kept points and ``_orient``),
in the same float operations, so outlier masks, normals and quality are bit-identical to it (checked by
test/test_grid_kernels.py against the numpy path, which stays selectable: ``PreprocessConfig.grid_backend``).

Why compiled: the numpy path makes some forty full-grid float32 temporaries and five scipy ``uniform_filter`` passes
per scan (~40 ms on a 180k-point scan here); these kernels stream over the grid a few times, in cache.

Rules kept for bit identity (change one and the test fails):

- float32 arithmetic in numpy's evaluation order, every constant a float32 (numba would promote ``2 * float32`` to
  float64), and no ``fastmath`` (LLVM then neither reorders sums nor fuses multiply-adds);
- box means exactly as ``scipy.ndimage.uniform_filter(mode="constant", cval=0)``: axis 0, then axis 1 on the
  float32-rounded result; along each line a float64 running sum over the zero-padded line (the first window summed
  in order, then ``tmp += in[i + size2] - in[i - size1 - 1]``), output ``float32(tmp / size)``.

Threads: the kernels that write cell by cell run in parallel by blocks of rows (xmetro_ros.compute.threads: the
caller's numba thread count, passed down as ``nt``); each cell is written by one block with the same float
operations, so the bits do not depend on the thread count (test/test_compute_threads.py).

Compile cost: ``cache=True`` writes the machine code to ``__pycache__`` (or ``NUMBA_CACHE_DIR``); the first call in
a fresh environment compiles (with the judge's other parallel kernels ~1 min at load 2, docs/performance.md), later
processes load it (0.5-1 s). ``scan_handler.warm_up`` (called when a ScanHandler is made, i.e. at node start) does
that.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
from numba import njit, prange

from ..compute.threads import row_blocks

__all__ = ["box_mean", "grid_normals_planes", "grid_outliers", "kept_normals", "orient_rows", "planes", "warm_up"]

# numpy float semantics: x / 0 → inf/nan, no raise
_JIT: dict[str, Any] = {"cache": True, "nogil": True, "error_model": "numpy"}
# Parallel drivers: each hands blocks of rows (of columns for the running sums down the columns) to the serial
# kernel below it, compiled on its own so that it stays vectorised (a prange over the loop body itself ran 2-4x
# slower per thread here). Every cell is written by one block with the serial float operations: the same bits at
# any thread count.
_PAR: dict[str, Any] = {**_JIT, "parallel": True}
_F0 = np.float32(0.0)
_F1 = np.float32(1.0)
_F2 = np.float32(2.0)
_FH = np.float32(0.5)


@njit(**_JIT)
def _box_axis0(a: np.ndarray, size: int, out: np.ndarray) -> None:
    """scipy uniform_filter1d(axis=0, mode="constant") of float32 (H, W) into out; rows outer for contiguity, the
    rows walked with a local index (so that the loop vectorises). One thread: the running sums are memory-bound,
    and column blocks on two threads were slower (0.23-0.29 vs 0.13 ms on a 348k-cell grid here: the blocks'
    boundaries share cache lines in every row)."""
    h, n = a.shape
    s1 = size // 2
    s2 = size - s1 - 1
    tmp = np.zeros(n, np.float64)
    for r in range(-s1, s2 + 1):  # the first window, in order (zero padding added too: -0.0 + 0.0 is +0.0)
        if 0 <= r < h:
            row = a[r]
            for k in range(n):
                tmp[k] += np.float64(row[k])
        else:
            for k in range(n):
                tmp[k] += 0.0
    o0 = out[0]
    for k in range(n):
        o0[k] = np.float32(tmp[k] / size)
    for i in range(1, h):
        ra = i + s2
        rb = i - s1 - 1
        oi = out[i]
        if ra < h and rb >= 0:
            ar = a[ra]
            br = a[rb]
            for k in range(n):
                tmp[k] += np.float64(ar[k]) - np.float64(br[k])
                oi[k] = np.float32(tmp[k] / size)
        else:
            for k in range(n):
                va = np.float64(a[ra, k]) if ra < h else 0.0
                vb = np.float64(a[rb, k]) if rb >= 0 else 0.0
                tmp[k] += va - vb
                oi[k] = np.float32(tmp[k] / size)


@njit(**_JIT)
def _box_axis1_rows(a: np.ndarray, size: int, out: np.ndarray, r0: int, r1: int) -> None:
    """scipy uniform_filter1d(axis=1, mode="constant") of rows r0:r1 of float32 (H, W) into out."""
    w = a.shape[1]
    s1 = size // 2
    s2 = size - s1 - 1
    for i in range(r0, r1):
        tmp = 0.0
        for c in range(-s1, s2 + 1):
            if 0 <= c < w:
                tmp += np.float64(a[i, c])
            else:
                tmp += 0.0
        out[i, 0] = np.float32(tmp / size)
        for j in range(1, w):
            ca = j + s2
            cb = j - s1 - 1
            va = np.float64(a[i, ca]) if ca < w else 0.0
            vb = np.float64(a[i, cb]) if cb >= 0 else 0.0
            tmp += va - vb
            out[i, j] = np.float32(tmp / size)


@njit(**_PAR)
def _box_axis1(a: np.ndarray, size: int, out: np.ndarray, nt: int) -> None:
    h = a.shape[0]
    nb = row_blocks(h, nt)
    for b in prange(nb):
        _box_axis1_rows(a, size, out, b * h // nb, (b + 1) * h // nb)


@njit(**_JIT)
def _box(a: np.ndarray, size: int, out: np.ndarray, scratch: np.ndarray, nt: int) -> None:
    if size == 1:  # scipy skips axes of size 1: a copy (-0.0 stays -0.0)
        out[:] = a
        return
    _box_axis0(a, size, scratch)
    _box_axis1(scratch, size, out, nt)


def box_mean(a: np.ndarray, size: int) -> np.ndarray:
    """``scipy.ndimage.uniform_filter(a, size, mode="constant")`` of a float32 (H, W) array, bit for bit."""
    a = np.ascontiguousarray(a, dtype=np.float32)
    out = np.empty_like(a)
    _box(a, int(size), out, np.empty_like(a), numba.get_num_threads())
    return out


@njit(**_JIT)
def _planes_rows(pts: np.ndarray, x: np.ndarray, y: np.ndarray, z: np.ndarray, valid: np.ndarray, r0: int,
                 r1: int) -> int:
    n = 0
    for i in range(r0, r1):
        for j in range(pts.shape[1]):
            a = np.float32(pts[i, j, 0])  # cast first: a float64 beyond float32 range is invalid, as in numpy
            b = np.float32(pts[i, j, 1])
            c = np.float32(pts[i, j, 2])
            ok = np.isfinite(a) and np.isfinite(b) and np.isfinite(c)
            valid[i, j] = ok
            if ok:
                x[i, j], y[i, j], z[i, j] = a, b, c
                n += 1
            else:
                x[i, j] = y[i, j] = z[i, j] = np.nan
    return n


@njit(**_PAR)
def _planes(pts: np.ndarray, nt: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """(X, Y, Z float32 (H, W) with NaN in invalid cells, valid (H, W), count) of (H, W, 3) points (any float)."""
    h, w = pts.shape[0], pts.shape[1]
    x = np.empty((h, w), np.float32)
    y = np.empty((h, w), np.float32)
    z = np.empty((h, w), np.float32)
    valid = np.empty((h, w), np.bool_)
    nb = row_blocks(h, nt)
    counts = np.zeros(nb, np.int64)
    for b in prange(nb):
        counts[b] = _planes_rows(pts, x, y, z, valid, b * h // nb, (b + 1) * h // nb)
    return x, y, z, valid, int(counts.sum())


def planes(grid: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """(X, Y, Z, valid, number valid) of an (H, W, 3) grid, as ``preprocess._planes`` (plus the count)."""
    return _planes(np.ascontiguousarray(grid), numba.get_num_threads())


@njit(inline="always", **_JIT)
def _step(x, y, z, i0, j0, i1, j1):
    """Distance between cells (i0, j0) and (i1, j1), float32 (NaN where either is NaN)."""
    dx = x[i1, j1] - x[i0, j0]
    dy = y[i1, j1] - y[i0, j0]
    dz = z[i1, j1] - z[i0, j0]
    return np.sqrt(dx * dx + dy * dy + dz * dz)


@njit(inline="always", **_JIT)
def _chord(x, y, z, ia, ja, i, j, ib, jb):
    """Chord offset |p_a + p_b − 2 p| / 2 of cell (i, j) between (ia, ja) and (ib, jb), float32."""
    kx = x[ia, ja] + x[ib, jb] - _F2 * x[i, j]
    ky = y[ia, ja] + y[ib, jb] - _F2 * y[i, j]
    kz = z[ia, ja] + z[ib, jb] - _F2 * z[i, j]
    return _FH * np.sqrt(kx * kx + ky * ky + kz * kz)


@njit(**_JIT)
def _offsets_nearest_rows(x, y, z, offset, nearest, r0, r1):
    h, w = x.shape
    for i in range(r0, r1):
        for j in range(w):
            nb = np.float32(np.inf)
            of = np.float32(np.inf)
            if i + 1 < h:
                s = _step(x, y, z, i, j, i + 1, j)
                if s < nb:
                    nb = s
            if i >= 1:
                s = _step(x, y, z, i - 1, j, i, j)
                if s < nb:
                    nb = s
            if j + 1 < w:
                s = _step(x, y, z, i, j, i, j + 1)
                if s < nb:
                    nb = s
            if j >= 1:
                s = _step(x, y, z, i, j - 1, i, j)
                if s < nb:
                    nb = s
            if 1 <= i < h - 1:
                o = _chord(x, y, z, i - 1, j, i, j, i + 1, j)
                if o < of:
                    of = o
            if 1 <= j < w - 1:
                o = _chord(x, y, z, i, j - 1, i, j, i, j + 1)
                if o < of:
                    of = o
            nearest[i, j] = nb
            offset[i, j] = of


@njit(**_PAR)
def _offsets_nearest(x, y, z, nt):
    """Per cell: the smallest chord offset |p- + p+ - 2p| / 2 over the grid directions with both neighbours (inf:
    none) and the distance to the nearest valid 4-neighbour (inf: none). NaN steps never win (a NaN is never
    smaller), so each minimum is that of its finite candidates in any order: each cell from its own neighbours
    (a step's two ends compute it alike: lower cell → higher cell)."""
    h, w = x.shape
    offset = np.empty((h, w), np.float32)
    nearest = np.empty((h, w), np.float32)
    nb = row_blocks(h, nt)
    for b in prange(nb):
        _offsets_nearest_rows(x, y, z, offset, nearest, b * h // nb, (b + 1) * h // nb)
    return offset, nearest


@njit(**_JIT)
def _spacing_sample(nearest: np.ndarray, max_samples: int) -> np.ndarray:
    """``nearest[isfinite(nearest)][::max(1, count // max_samples)]`` (flat order), as the numpy path samples it."""
    flat = nearest.ravel()
    n = 0
    for k in range(flat.size):
        if np.isfinite(flat[k]):
            n += 1
    stride = max(1, n // max_samples)
    out = np.empty((n + stride - 1) // stride, np.float32)
    seen = 0
    m = 0
    for k in range(flat.size):
        if np.isfinite(flat[k]):
            if seen % stride == 0:
                out[m] = flat[k]
                m += 1
            seen += 1
    return out


@njit(**_JIT)
def _judged_rows(valid, offset, judged, off0, r0, r1):
    for i in range(r0, r1):
        for j in range(valid.shape[1]):
            jd = valid[i, j] and np.isfinite(offset[i, j])
            judged[i, j] = _F1 if jd else _F0
            off0[i, j] = offset[i, j] if jd else _F0


@njit(**_JIT)
def _mask_rows(valid, offset, nearest, judged, cnt, mean, min_offset, offset_factor, gap_thr, out, r0, r1):
    for i in range(r0, r1):
        for j in range(valid.shape[1]):
            if judged[i, j] != _F0:
                m = mean[i, j]
                if cnt[i, j] > _F0:
                    m = m / cnt[i, j]
                t = offset_factor * m
                thr = min_offset if min_offset >= t else t  # np.maximum (no NaN here)
                if offset[i, j] > thr:
                    out[i, j] = True
            if valid[i, j]:
                nb = nearest[i, j]
                if not np.isfinite(nb) or nb > gap_thr:
                    out[i, j] = True


@njit(**_PAR)
def _outlier_mask(valid, offset, nearest, min_offset, offset_factor, gap_thr, scale_window, nt):
    """The outlier rule of ``preprocess._grid_outliers_planes`` from the offsets and nearest distances."""
    h, w = valid.shape
    judged = np.empty((h, w), np.float32)
    off0 = np.empty((h, w), np.float32)
    nb = row_blocks(h, nt)
    for b in prange(nb):
        _judged_rows(valid, offset, judged, off0, b * h // nb, (b + 1) * h // nb)
    scratch = np.empty((h, w), np.float32)
    cnt = np.empty((h, w), np.float32)
    mean = np.empty((h, w), np.float32)
    _box(judged, scale_window, cnt, scratch, nt)
    _box(off0, scale_window, mean, scratch, nt)
    out = np.zeros((h, w), np.bool_)
    for b in prange(nb):
        _mask_rows(valid, offset, nearest, judged, cnt, mean, min_offset, offset_factor, gap_thr, out,
                   b * h // nb, (b + 1) * h // nb)
    return out


def grid_outliers(
    x: np.ndarray, y: np.ndarray, z: np.ndarray, valid: np.ndarray, min_offset_mm: float, offset_factor: float,
    gap_factor: float, scale_window: int,
) -> np.ndarray:
    """Outlier mask (H, W) bool of the planes, bit-identical to ``preprocess._grid_outliers_planes``."""
    nt = numba.get_num_threads()
    offset, nearest = _offsets_nearest(x, y, z, nt)
    sample = _spacing_sample(nearest, 20000)
    gap_thr = np.float32(np.inf)
    if sample.size:
        spacing = float(np.median(sample))  # np.median, as the numpy path (a float32 middle or mean of two)
        # numpy compares the float32 distances with the Python float threshold in float32 (NEP 50: weak scalar)
        gap_thr = np.float32(gap_factor * max(spacing, 1e-9))
    return _outlier_mask(valid, offset, nearest, np.float32(min_offset_mm), np.float32(offset_factor), gap_thr,
                         int(scale_window), nt)


@njit(**_PAR)
def _raw_normals(x, y, z, valid, nt):
    """Unit raw normals (column tangent × row tangent; 0 where undefined), as ``preprocess._grid_normals_planes``."""
    h, w = valid.shape
    nx = np.empty((h, w), np.float32)
    ny = np.empty((h, w), np.float32)
    nz = np.empty((h, w), np.float32)
    nb = row_blocks(h, nt)
    for b in prange(nb):
        _raw_normals_rows(x, y, z, valid, nx, ny, nz, b * h // nb, (b + 1) * h // nb)
    return nx, ny, nz


@njit(**_JIT)
def _raw_normals_rows(x, y, z, valid, nx, ny, nz, r0, r1):
    h, w = valid.shape
    for i in range(r0, r1):
        for j in range(w):
            # central difference = (0 + forward f[i]) + forward f[i-1]; f = (c[i+1] - c[i]) * both (0 across holes)
            ax = ay = az = bx = by = bz = _F0
            v = valid[i, j]
            if i + 1 < h:
                both = _F1 if (v and valid[i + 1, j]) else _F0
                ax += (_zv(x, i + 1, j, valid) - _zv(x, i, j, valid)) * both
                ay += (_zv(y, i + 1, j, valid) - _zv(y, i, j, valid)) * both
                az += (_zv(z, i + 1, j, valid) - _zv(z, i, j, valid)) * both
            if i >= 1:
                both = _F1 if (valid[i - 1, j] and v) else _F0
                ax += (_zv(x, i, j, valid) - _zv(x, i - 1, j, valid)) * both
                ay += (_zv(y, i, j, valid) - _zv(y, i - 1, j, valid)) * both
                az += (_zv(z, i, j, valid) - _zv(z, i - 1, j, valid)) * both
            if j + 1 < w:
                both = _F1 if (v and valid[i, j + 1]) else _F0
                bx += (_zv(x, i, j + 1, valid) - _zv(x, i, j, valid)) * both
                by += (_zv(y, i, j + 1, valid) - _zv(y, i, j, valid)) * both
                bz += (_zv(z, i, j + 1, valid) - _zv(z, i, j, valid)) * both
            if j >= 1:
                both = _F1 if (valid[i, j - 1] and v) else _F0
                bx += (_zv(x, i, j, valid) - _zv(x, i, j - 1, valid)) * both
                by += (_zv(y, i, j, valid) - _zv(y, i, j - 1, valid)) * both
                bz += (_zv(z, i, j, valid) - _zv(z, i, j - 1, valid)) * both
            cx = ay * bz - az * by
            cy = az * bx - ax * bz
            cz = ax * by - ay * bx
            nn = np.sqrt(cx * cx + cy * cy + cz * cz)
            inv = _F1 / nn if (v and nn > _F0) else _F0
            nx[i, j] = cx * inv
            ny[i, j] = cy * inv
            nz[i, j] = cz * inv


@njit(inline="always", **_JIT)
def _zv(c, i, j, valid):
    """The coordinate with holes read as 0 (the numpy path's ``np.where(valid, c, 0)``)."""
    return c[i, j] if valid[i, j] else _F0


@njit(**_JIT)
def _smoothed(x, y, z, valid, window, nt):
    nx, ny, nz = _raw_normals(x, y, z, valid, nt)
    if window > 1:  # window mean of the raw unit normals
        scratch = np.empty_like(nx)
        sx = np.empty_like(nx)
        sy = np.empty_like(nx)
        sz = np.empty_like(nx)
        _box(nx, window, sx, scratch, nt)
        _box(ny, window, sy, scratch, nt)
        _box(nz, window, sz, scratch, nt)
        return sx, sy, sz
    return nx, ny, nz


@njit(inline="always", **_JIT)
def _finish(sx, sy, sz, ok_in):
    """Normalised normal and quality of one cell from its window-mean normal (NaN normal, 0 quality: undefined)."""
    q = np.sqrt(sx * sx + sy * sy + sz * sz)
    ok = ok_in and q > np.float32(1e-6)
    inv = _F1 / q if ok else np.float32(np.nan)
    if not ok:
        q = _F0
    elif q > _F1:
        q = _F1
    return sx * inv, sy * inv, sz * inv, q


@njit(**_JIT)
def _finish_rows(sx, sy, sz, q, valid, r0, r1):
    for i in range(r0, r1):
        for j in range(valid.shape[1]):
            sx[i, j], sy[i, j], sz[i, j], q[i, j] = _finish(sx[i, j], sy[i, j], sz[i, j], valid[i, j])


@njit(**_PAR)
def _normals_planes(x, y, z, valid, window, nt):
    sx, sy, sz = _smoothed(x, y, z, valid, window, nt)
    h, w = valid.shape
    q = np.empty((h, w), np.float32)
    nb = row_blocks(h, nt)
    for b in prange(nb):
        _finish_rows(sx, sy, sz, q, valid, b * h // nb, (b + 1) * h // nb)
    return sx, sy, sz, q


def grid_normals_planes(
    x: np.ndarray, y: np.ndarray, z: np.ndarray, valid: np.ndarray, window: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(nx, ny, nz, quality) float32 (H, W) planes, bit-identical to ``preprocess._grid_normals_planes``."""
    return _normals_planes(x, y, z, valid, int(window), numba.get_num_threads())


@njit(**_JIT)
def _count_rows(valid, r0, r1):
    c = 0
    for i in range(r0, r1):
        for j in range(valid.shape[1]):
            if valid[i, j]:
                c += 1
    return c


@njit(**_JIT)
def _gather_rows(pts, sx, sy, sz, valid, index, normals, quality, points, r, r0, r1):
    w = valid.shape[1]
    for i in range(r0, r1):
        for j in range(w):
            if valid[i, j]:
                index[r] = i * w + j
                normals[r, 0], normals[r, 1], normals[r, 2], quality[r] = _finish(sx[i, j], sy[i, j], sz[i, j],
                                                                                  True)
                points[r, 0] = np.float64(pts[i, j, 0])
                points[r, 1] = np.float64(pts[i, j, 1])
                points[r, 2] = np.float64(pts[i, j, 2])
                r += 1


@njit(**_PAR)
def _kept(pts, x, y, z, valid, window, nt):
    """Normals and quality of the valid cells only, gathered in flat order with their flat index and their points
    (float64, from the input grid) — one pass, no full-grid normal planes kept; each block of rows writes from
    the count of the blocks before it."""
    sx, sy, sz = _smoothed(x, y, z, valid, window, nt)
    h = valid.shape[0]
    nb = row_blocks(h, nt)
    start = np.zeros(nb + 1, np.int64)
    for b in prange(nb):
        start[b + 1] = _count_rows(valid, b * h // nb, (b + 1) * h // nb)
    for b in range(nb):
        start[b + 1] += start[b]
    m = start[nb]
    index = np.empty(m, np.int64)
    normals = np.empty((m, 3), np.float32)
    quality = np.empty(m, np.float32)
    points = np.empty((m, 3), np.float64)
    for b in prange(nb):
        _gather_rows(pts, sx, sy, sz, valid, index, normals, quality, points, start[b], b * h // nb,
                     (b + 1) * h // nb)
    return index, normals, quality, points


def kept_normals(
    pts: np.ndarray, x: np.ndarray, y: np.ndarray, z: np.ndarray, valid: np.ndarray, window: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(index (M,) int64 flat, normals (M, 3) float32, quality (M,) float32, points (M, 3) float64) of the valid
    cells of the planes; ``pts`` is the (H, W, 3) input the points are read from (mm)."""
    return _kept(np.ascontiguousarray(pts), x, y, z, valid, int(window), numba.get_num_threads())


@njit(**_PAR)
def _orient_rows(normals, quality, ref, nt):
    m = normals.shape[0]
    nb = row_blocks(m, nt)
    for b in prange(nb):
        _orient_range(normals, quality, ref, b * m // nb, (b + 1) * m // nb)


@njit(**_JIT)
def _orient_range(normals, quality, ref, r0, r1):
    for r in range(r0, r1):
        n0, n1, n2 = normals[r, 0], normals[r, 1], normals[r, 2]
        if not (np.isfinite(n0) and np.isfinite(n1) and np.isfinite(n2)):  # undefined normal → the reference, q 0
            n0, n1, n2 = ref[r, 0], ref[r, 1], ref[r, 2]
            quality[r] = _F0
        d = n0 * ref[r, 0] + n1 * ref[r, 1] + n2 * ref[r, 2]  # einsum's float32 order on rows of 3
        s = np.float32(-1.0) if d < _F0 else _F1
        normals[r, 0] = n0 * s
        normals[r, 1] = n1 * s
        normals[r, 2] = n2 * s


def orient_rows(normals: np.ndarray, quality: np.ndarray, ref: np.ndarray) -> None:
    """In place: rows of ``normals`` (M, 3) float32 that are not finite become ``ref`` (quality 0); then every row
    is flipped to a non-negative dot with ``ref`` (M, 3) float32 — ``prepare_scan``'s bad-normal rule and
    ``preprocess._orient`` in one pass."""
    _orient_rows(normals, quality, np.ascontiguousarray(ref, dtype=np.float32), numba.get_num_threads())


def warm_up() -> float:
    """Compile (or load from the cache) every kernel for float32 and float64 input grids; returns seconds taken."""
    import time

    t = time.perf_counter()
    for dt in (np.float32, np.float64):
        g = np.zeros((5, 6, 3), dt)
        g[..., 0] = np.arange(6)
        g[..., 1] = np.arange(5)[:, None]
        g[2, 3] = np.nan
        x, y, z, valid, _ = planes(g)
        grid_outliers(x, y, z, valid, 0.05, 6.0, 20.0, 9)
        grid_normals_planes(x, y, z, valid, 5)
        _idx, n, q, _p = kept_normals(g, x, y, z, valid, 5)
        orient_rows(n, q, np.ones_like(n))
    box_mean(np.zeros((3, 3), np.float32), 3)
    return time.perf_counter() - t
