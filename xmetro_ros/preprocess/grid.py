"""Organized-grid path (H profiles × W points): outlier test and window-mean cross-product normals on the grid,
float32, in numpy (the reference) or compiled (:mod:`.grid_kernels`, bit-identical)."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from .config import GRID_BACKENDS, PreprocessError


def _check_grid_window(window: int) -> None:
    if window < 1 or window % 2 == 0:
        raise PreprocessError(f"grid_window must be an odd number >= 1, got {window}")


def normals_grid(
    points: np.ndarray, grid_shape: tuple[int, int], grid_index: np.ndarray, *, grid_window: int = 5,
    backend: str = "numba",
) -> tuple[np.ndarray, np.ndarray]:
    """Organized-grid normals of finite points (N, 3) mm at flat indices ``grid_index`` (N,) of an ``grid_shape``
    (H, W) grid: the normalised ``grid_window`` × ``grid_window`` window mean of the raw cross-product normals
    (see :func:`grid_normals`). Returns (normals (N, 3) float32, NaN where undefined, sign the grid's; quality (N,)
    float32). ``backend``: "numba" or "numpy" (bit-identical)."""
    h, w = (int(x) for x in grid_shape)
    gi = np.asarray(grid_index, dtype=np.int64)
    if gi.shape != (len(points),) or (len(gi) and (gi.min() < 0 or gi.max() >= h * w)):
        raise PreprocessError(f"grid_index must be {len(points)} flat indices into a {h}x{w} grid")
    _check_grid_window(grid_window)
    grid = np.full((h * w, 3), np.nan, dtype=np.float32)
    grid[gi] = points
    nx, ny, nz, q = _grid_normal_planes(*_planes(grid.reshape(h, w, 3)), grid_window, backend)
    normals = np.stack([nx.reshape(-1)[gi], ny.reshape(-1)[gi], nz.reshape(-1)[gi]], axis=1)
    return normals, q.reshape(-1)[gi]




def _planes(grid: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(X, Y, Z, valid) contiguous float32 (H, W) planes of an (H, W, 3) grid; invalid cells hold NaN in X, Y, Z."""
    g = np.asarray(grid)
    if g.ndim != 3 or g.shape[2] != 3:
        raise PreprocessError(f"grid must have shape (H, W, 3), got {g.shape}")
    x, y, z = np.moveaxis(g, 2, 0).astype(np.float32)  # one copy, channel-first: every op below is contiguous
    valid = np.isfinite(x)
    valid &= np.isfinite(y)
    valid &= np.isfinite(z)
    if not valid.all():
        inv = ~valid
        x[inv] = np.nan
        y[inv] = np.nan
        z[inv] = np.nan
    return x, y, z, valid


def _grid_outliers_planes(
    x: np.ndarray, y: np.ndarray, z: np.ndarray, valid: np.ndarray, min_offset_mm: float, offset_factor: float,
    gap_factor: float, scale_window: int = 9,
) -> np.ndarray:
    h, w = valid.shape
    offset = np.full((h, w), np.inf, dtype=np.float32)
    nearest = np.full((h, w), np.inf, dtype=np.float32)
    with np.errstate(invalid="ignore"):
        for axis in (0, 1):
            if valid.shape[axis] < 2:
                continue
            a = (slice(None, -1), slice(None)) if axis == 0 else (slice(None), slice(None, -1))
            b = (slice(1, None), slice(None)) if axis == 0 else (slice(None), slice(1, None))
            # step length between consecutive cells along the axis (NaN where either is a hole)
            step = np.sqrt((x[b] - x[a]) ** 2 + (y[b] - y[a]) ** 2 + (z[b] - z[a]) ** 2)
            np.fmin(nearest[a], step, out=nearest[a])
            np.fmin(nearest[b], step, out=nearest[b])
            if valid.shape[axis] < 3:
                continue
            c = (slice(1, -1), slice(None)) if axis == 0 else (slice(None), slice(1, -1))
            p = (slice(None, -2), slice(None)) if axis == 0 else (slice(None), slice(None, -2))
            n = (slice(2, None), slice(None)) if axis == 0 else (slice(None), slice(2, None))
            # offset of the point from the chord midpoint of its two neighbours: |p- + p+ - 2p| / 2
            k2 = (x[p] + x[n] - 2 * x[c]) ** 2 + (y[p] + y[n] - 2 * y[c]) ** 2 + (z[p] + z[n] - 2 * z[c]) ** 2
            np.fmin(offset[c], 0.5 * np.sqrt(k2), out=offset[c])  # NaN (missing neighbour): other direction
    out = np.zeros((h, w), dtype=bool)
    judged = valid & np.isfinite(offset)
    if judged.any():
        # local noise scale: window mean of the offsets of the judged cells
        off0 = np.where(judged, offset, np.float32(0))
        cnt = ndimage.uniform_filter(judged.astype(np.float32), size=scale_window, mode="constant")
        mean = ndimage.uniform_filter(off0, size=scale_window, mode="constant")
        np.divide(mean, cnt, out=mean, where=cnt > 0)
        thr = np.maximum(np.float32(min_offset_mm), np.float32(offset_factor) * mean)
        out = judged & (offset > thr)
    has_nb = valid & np.isfinite(nearest)
    if has_nb.any():
        spacing = float(np.median(nearest[has_nb][:: max(1, int(has_nb.sum()) // 20000)]))
        out |= has_nb & (nearest > gap_factor * max(spacing, 1e-9))
    out |= valid & ~np.isfinite(nearest)  # no valid 4-neighbour at all: can be neither judged nor given a normal
    return out


def _grid_outlier_mask(
    x: np.ndarray, y: np.ndarray, z: np.ndarray, valid: np.ndarray, min_offset_mm: float, offset_factor: float,
    gap_factor: float, scale_window: int, backend: str,
) -> np.ndarray:
    """The grid outlier mask by ``backend`` ("numba": compiled kernels; "numpy"): bit-identical results."""
    if backend == "numba":
        from .grid_kernels import grid_outliers as compiled_grid_outliers

        return compiled_grid_outliers(x, y, z, valid, min_offset_mm, offset_factor, gap_factor, scale_window)
    if backend != "numpy":
        raise PreprocessError(f"grid backend must be one of {GRID_BACKENDS}, got {backend!r}")
    return _grid_outliers_planes(x, y, z, valid, min_offset_mm, offset_factor, gap_factor, scale_window)


def _grid_normal_planes(
    x: np.ndarray, y: np.ndarray, z: np.ndarray, valid: np.ndarray, window: int, backend: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(nx, ny, nz, quality) planes by ``backend`` ("numba" or "numpy"): bit-identical results."""
    if backend == "numba":
        from .grid_kernels import grid_normals_planes

        return grid_normals_planes(x, y, z, valid, window)
    if backend != "numpy":
        raise PreprocessError(f"grid backend must be one of {GRID_BACKENDS}, got {backend!r}")
    return _grid_normals_planes(x, y, z, valid, window)[:4]


def grid_outliers(
    grid: np.ndarray, min_offset_mm: float = 0.05, offset_factor: float = 6.0, gap_factor: float = 20.0,
    scale_window: int = 9, backend: str = "numba",
) -> np.ndarray:
    """Outliers of an organized cloud (H, W, 3) mm with NaN holes. Returns a boolean (H, W) mask (True = outlier;
    holes are never outliers).

    Offset along a grid direction = |p[i-1] + p[i+1] - 2 p[i]| / 2: the distance of the point from the chord
    midpoint of its two neighbours (≈ h² / 8R on a smooth surface, ≈ δ for a return displaced by δ). A spurious
    return is off in both directions, its neighbours in one only: the score is the minimum over the directions
    that have both neighbours. Outlier: score > max(min_offset_mm, offset_factor × the window mean of the scores
    over ``scale_window`` × ``scale_window`` cells) — a local noise scale, since noise grows toward grazing
    incidence. Points whose nearest valid 4-neighbour is farther than gap_factor × the median spacing, or that
    have none, are outliers too (isolated returns). ``backend``: "numba" (compiled) or "numpy" (bit-identical)."""
    x, y, z, valid = _planes(grid)
    return _grid_outlier_mask(x, y, z, valid, min_offset_mm, offset_factor, gap_factor, scale_window, backend)


def _grid_normals_planes(
    x: np.ndarray, y: np.ndarray, z: np.ndarray, valid: np.ndarray, window: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    h, w = valid.shape
    comps = [np.where(valid, c, np.float32(0)) for c in (x, y, z)]
    tangents = []
    for axis in (0, 1):
        a = (slice(None, -1), slice(None)) if axis == 0 else (slice(None), slice(None, -1))
        b = (slice(1, None), slice(None)) if axis == 0 else (slice(None), slice(1, None))
        both = (valid[a] & valid[b]).astype(np.float32)
        t = []
        for c in comps:
            f = (c[b] - c[a]) * both  # forward difference, 0 across a hole
            d = np.zeros((h, w), dtype=np.float32)
            d[a] += f  # central difference = f[i-1] + f[i]: one-sided where a neighbour is missing
            d[b] += f
            t.append(d)
        tangents.append(t)
    (ax, ay, az), (bx, by, bz) = tangents  # along columns (profile to profile) and along rows (the laser line)
    # raw per-cell normal = t_col × t_row (a consistent sign over the whole grid), normalised; 0 where undefined
    nx = ay * bz - az * by
    ny = az * bx - ax * bz
    nz = ax * by - ay * bx
    nn = np.sqrt(nx * nx + ny * ny + nz * nz)
    inv = np.divide(np.float32(1), nn, out=np.zeros_like(nn), where=valid & (nn > 0))
    nx *= inv
    ny *= inv
    nz *= inv
    if window > 1:  # window mean of the raw unit normals: plane-fit-like smoothing and the quality in one pass
        nx, ny, nz = (ndimage.uniform_filter(c, size=window, mode="constant") for c in (nx, ny, nz))
    q = np.sqrt(nx * nx + ny * ny + nz * nz)
    ok = valid & (q > 1e-6)
    inv = np.divide(np.float32(1), q, out=np.full_like(q, np.nan), where=ok)
    nx *= inv
    ny *= inv
    nz *= inv
    np.clip(q, 0, 1, out=q)
    q[~ok] = 0
    return nx, ny, nz, q, ok


def grid_normals(grid: np.ndarray, window: int = 5, backend: str = "numba") -> tuple[np.ndarray, np.ndarray]:
    """Normals and quality of an organized cloud (H, W, 3) mm with NaN holes, fully vectorised in float32.

    Raw normal per cell = (column tangent × row tangent) from NaN-aware central differences (one-sided at holes),
    normalised; the normal is the normalised mean of the raw unit normals over a ``window`` × ``window`` box and
    the quality is the length of that mean in [0, 1] (1 = full, planar, noise-free window; missing cells count 0).
    Returns (normals (H, W, 3) float32 unit, NaN where undefined; quality (H, W) float32). Orientation is the
    grid's (consistent over the grid, sign arbitrary): ``estimate_normals`` / ``prepare_scan`` orient them.
    ``backend``: "numba" (compiled) or "numpy" (bit-identical)."""
    if window < 1 or window % 2 == 0:
        raise PreprocessError(f"window must be an odd number >= 1, got {window}")
    x, y, z, valid = _planes(grid)
    nx, ny, nz, q = _grid_normal_planes(x, y, z, valid, window, backend)
    return np.stack([nx, ny, nz], axis=2), q


