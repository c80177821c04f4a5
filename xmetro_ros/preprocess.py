"""Pre-processing of a scan (the study's §3.3): outlier removal and surface normals, oriented consistently.

Two paths:

- **Organized grid** (H profiles × W points, the virtual and live scanners): fully vectorised on the grid, float32.
  Outliers are points far from the chord of their two grid neighbours in *both* grid directions (a spurious
  return is off along its profile and its column; its neighbours only along one), relative to a local noise
  scale, plus points with no valid 4-neighbour within ``grid_gap_factor`` median spacings. Raw normals are the
  cross product of the column and row tangents (NaN-aware central differences); the normal is the normalised
  mean of the raw unit normals over a ``grid_window`` × ``grid_window`` box (a plane-fit-like average) and the
  quality is the length of that mean (1 = full, planar, noise-free window; lower near holes, edges, noise).
- **Unorganized** (N × 3): open3d statistical outlier removal and KD-tree normal estimation (hybrid radius / max_nn),
  as in the study, after removing exact duplicate points (real bags hold many; they break the neighbour statistics
  and make open3d slow). Quality = 1 − nearest-neighbour distance / radius (clipped to [0, 1]).

Orientation: normals are flipped to have a positive dot product with ``toward`` (per point, e.g. toward the laser
source, which is outward for the visible side of a closed artifact); without ``toward``, away from the centroid.
Lengths in mm, scan frame. See docs/features.md for the agreement between the two paths.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from .geometry import HeadPose, PointGeometry, point_geometry
from .scan import Scan
from .scanner import ScannerModel, ScanSettings

__all__ = [
    "PreprocessConfig",
    "Prepared",
    "PreprocessError",
    "remove_outliers",
    "estimate_normals",
    "grid_outliers",
    "grid_normals",
    "dedupe",
    "prepare_scan",
]


class PreprocessError(ValueError):
    """A cloud that cannot be pre-processed (empty, wrong shape, no finite point, too few points left)."""


@dataclass(frozen=True)
class PreprocessConfig:
    """Pre-processing parameters (lengths in mm).

    Attributes:
        nb_neighbors, std_ratio: open3d statistical outlier removal (unorganized path).
        normal_radius_mm, max_nn: open3d hybrid KD-tree search for normals (unorganized path).
        use_grid: use the organized-grid path when the scan is organized.
        grid_window: side of the box window (grid cells, odd) the grid normals are averaged over.
        grid_min_offset_mm: a point is an outlier when its offset from the chords of its grid neighbours (in both
            directions) exceeds this (mm) ...
        grid_offset_factor: ... and this many times the local mean offset (noise scale) over
            grid_scale_window × grid_scale_window cells (see grid_outliers).
        grid_gap_factor: a point whose nearest valid 4-neighbour is farther than this many median spacings is an
            outlier (isolated return).
        min_points: fewer valid points than this after cleaning → PreprocessError.
    """

    nb_neighbors: int = 20
    std_ratio: float = 2.0
    normal_radius_mm: float = 1.5
    max_nn: int = 30
    use_grid: bool = True
    grid_window: int = 5
    grid_min_offset_mm: float = 0.05
    grid_offset_factor: float = 6.0
    grid_scale_window: int = 9
    grid_gap_factor: float = 20.0
    min_points: int = 3


@dataclass
class Prepared:
    """A pre-processed scan: the kept points with their normals and geometry (scan frame, mm).

    Attributes:
        points: (M, 3) float64 kept points.
        normals: (M, 3) float32 unit normals, oriented toward the laser source (outward on closed artifacts).
        normal_quality: (M,) float32 in [0, 1] (see module doc); low = unreliable normal.
        index: (M,) flat indices of the kept points into the scan's grid (H*W) or list (N).
        outlier: (K,) flat indices of the finite points removed as outliers.
        fields: per-point fields of the kept points {name: (M,)}.
        settings, pose, scanner: how the scan was taken.
        geometry: PointGeometry of the kept points (float32 L, V, ...).
        shape: the scan's grid shape (H, W) or (N,).
    """

    points: np.ndarray
    normals: np.ndarray
    normal_quality: np.ndarray
    index: np.ndarray
    outlier: np.ndarray
    fields: dict[str, np.ndarray]
    settings: ScanSettings
    pose: HeadPose
    scanner: ScannerModel
    geometry: PointGeometry
    shape: tuple[int, ...] = ()
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.points)

    def subset(self, sel: np.ndarray) -> Prepared:
        """The same prepared scan restricted to rows ``sel`` (indices or boolean mask) of its kept points."""
        g = self.geometry
        return Prepared(
            points=self.points[sel],
            normals=self.normals[sel],
            normal_quality=self.normal_quality[sel],
            index=self.index[sel],
            outlier=self.outlier,
            fields={k: v[sel] for k, v in self.fields.items()},
            settings=self.settings,
            pose=self.pose,
            scanner=self.scanner,
            geometry=PointGeometry(g.L[sel], g.V[sel], g.source_distance[sel], g.standoff[sel], g.u[sel], g.s[sel]),
            shape=self.shape,
            meta=dict(self.meta),
        )


# ----------------------------------------------------------------------------------------------------------------
# helpers


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


def dedupe(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact duplicate points removed: (unique_index (U,), inverse (N,)) with points[unique_index][inverse] ==
    points. Hashes the coordinate bits (one 1-D sort, ~10× faster than ``np.unique(axis=0)``), verified exactly."""
    p = np.ascontiguousarray(points, dtype=np.float64)
    p = p + 0.0  # -0.0 → +0.0 so equal coordinates have equal bits
    bits = p.view(np.uint64).reshape(-1, 3)
    h = bits[:, 0] * np.uint64(0x9E3779B97F4A7C15) ^ bits[:, 1] * np.uint64(0xC2B2AE3D27D4EB4F)
    h ^= bits[:, 2] * np.uint64(0x165667B19E3779F9)
    _, first, inverse = np.unique(h, return_index=True, return_inverse=True)
    if not np.array_equal(p[first[inverse]], p):  # hash collision (never seen): exact but slower path
        _, first, inverse = np.unique(p, axis=0, return_index=True, return_inverse=True)
    return first, inverse.reshape(-1)


def _o3d_cloud(points: np.ndarray):
    import open3d as o3d

    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64)))


# ----------------------------------------------------------------------------------------------------------------
# unorganized path (open3d, as in the study)


def remove_outliers(points: np.ndarray, nb_neighbors: int = 20, std_ratio: float = 2.0) -> np.ndarray:
    """open3d statistical outlier removal on (N, 3) finite points (mm). Returns the boolean keep mask (N,).

    Exact duplicates are collapsed first (they would be each other's zero-distance neighbours) and share the
    verdict of their unique point."""
    p = _check_points(points)
    if nb_neighbors < 1 or not std_ratio > 0:
        raise PreprocessError(f"nb_neighbors must be >= 1 and std_ratio > 0, got {nb_neighbors}, {std_ratio}")
    first, inverse = dedupe(p)
    keep_u = np.zeros(len(first), dtype=bool)
    if len(first) <= nb_neighbors:
        keep_u[:] = True  # too few points for the statistic: keep all
    else:
        _, idx = _o3d_cloud(p[first]).remove_statistical_outlier(nb_neighbors=int(nb_neighbors), std_ratio=std_ratio)
        keep_u[np.asarray(idx, dtype=np.int64)] = True
    return keep_u[inverse]


def estimate_normals(
    points: np.ndarray,
    *,
    grid_shape: tuple[int, int] | None = None,
    grid_index: np.ndarray | None = None,
    radius_mm: float = 1.5,
    max_nn: int = 30,
    toward: np.ndarray | None = None,
    grid_window: int = 5,
) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (N, 3) float32 and a quality (N,) float32 in [0, 1] for finite points (N, 3), mm.

    With ``grid_shape=(H, W)`` and ``grid_index`` (flat index of each point into the H×W grid) the organized grid
    path is used (``grid_window`` cells); otherwise open3d KD-tree estimation (hybrid ``radius_mm`` / ``max_nn``).
    Normals are oriented to have a positive dot with ``toward`` ((N,3) or (3,)), or away from the centroid.
    Points without a usable neighbourhood get quality 0 and the orientation reference as normal."""
    p = _check_points(points)
    if grid_shape is not None:
        if grid_index is None:
            raise PreprocessError("grid_shape needs grid_index (flat index of each point into the grid)")
        h, w = (int(x) for x in grid_shape)
        gi = np.asarray(grid_index, dtype=np.int64)
        if gi.shape != (len(p),) or (len(gi) and (gi.min() < 0 or gi.max() >= h * w)):
            raise PreprocessError(f"grid_index must be {len(p)} flat indices into a {h}x{w} grid")
        grid = np.full((h * w, 3), np.nan, dtype=np.float32)
        grid[gi] = p
        if grid_window < 1 or grid_window % 2 == 0:
            raise PreprocessError(f"grid_window must be an odd number >= 1, got {grid_window}")
        nx, ny, nz, q, _ = _grid_normals_planes(*_planes(grid.reshape(h, w, 3)), grid_window)
        normals = np.stack([nx.reshape(-1)[gi], ny.reshape(-1)[gi], nz.reshape(-1)[gi]], axis=1)
        quality = q.reshape(-1)[gi]
    else:
        if not radius_mm > 0 or max_nn < 3:
            raise PreprocessError(f"radius_mm must be > 0 and max_nn >= 3, got {radius_mm}, {max_nn}")
        import open3d as o3d

        first, inverse = dedupe(p)
        pu = p[first]
        if len(pu) < 3:
            normals = np.zeros((len(p), 3), np.float32)
            quality = np.zeros(len(p), np.float32)
        else:
            pc = _o3d_cloud(pu)
            pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=float(radius_mm), max_nn=int(max_nn)))
            nu = np.asarray(pc.normals, dtype=np.float32)
            # Quality: 1 − (nearest-neighbour distance / radius), clipped: 0 for lone points (open3d gives them an
            # arbitrary normal), low in sparse regions. A neighbour-count query would double the cost of this path.
            dnn = np.asarray(pc.compute_nearest_neighbor_distance(), dtype=np.float32)
            qu = np.clip(1.0 - dnn / np.float32(radius_mm), 0.0, 1.0).astype(np.float32)
            normals, quality = nu[inverse], qu[inverse]
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
        normals[bad] = np.where(nr > 0, ref / np.where(nr > 0, nr, 1), np.float32([0, 0, 1]))
        quality = quality.copy()
        quality[bad] = 0.0
    return normals, np.asarray(quality, dtype=np.float32)


# ----------------------------------------------------------------------------------------------------------------
# organized grid path


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


def grid_outliers(
    grid: np.ndarray, min_offset_mm: float = 0.05, offset_factor: float = 6.0, gap_factor: float = 20.0,
    scale_window: int = 9,
) -> np.ndarray:
    """Outliers of an organized cloud (H, W, 3) mm with NaN holes. Returns a boolean (H, W) mask (True = outlier;
    holes are never outliers).

    Offset along a grid direction = |p[i-1] + p[i+1] - 2 p[i]| / 2: the distance of the point from the chord
    midpoint of its two neighbours (≈ h² / 8R on a smooth surface, ≈ δ for a return displaced by δ). A spurious
    return is off in both directions, its neighbours in one only: the score is the minimum over the directions
    that have both neighbours. Outlier: score > max(min_offset_mm, offset_factor × the window mean of the scores
    over ``scale_window`` × ``scale_window`` cells) — a local noise scale, since noise grows toward grazing
    incidence. Points whose nearest valid 4-neighbour is farther than gap_factor × the median spacing, or that
    have none, are outliers too (isolated returns)."""
    x, y, z, valid = _planes(grid)
    return _grid_outliers_planes(x, y, z, valid, min_offset_mm, offset_factor, gap_factor, scale_window)


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


def grid_normals(grid: np.ndarray, window: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Normals and quality of an organized cloud (H, W, 3) mm with NaN holes, fully vectorised in float32.

    Raw normal per cell = (column tangent × row tangent) from NaN-aware central differences (one-sided at holes),
    normalised; the normal is the normalised mean of the raw unit normals over a ``window`` × ``window`` box and
    the quality is the length of that mean in [0, 1] (1 = full, planar, noise-free window; missing cells count 0).
    Returns (normals (H, W, 3) float32 unit, NaN where undefined; quality (H, W) float32). Orientation is the
    grid's (consistent over the grid, sign arbitrary): ``estimate_normals`` / ``prepare_scan`` orient them."""
    if window < 1 or window % 2 == 0:
        raise PreprocessError(f"window must be an odd number >= 1, got {window}")
    x, y, z, valid = _planes(grid)
    nx, ny, nz, q, _ = _grid_normals_planes(x, y, z, valid, window)
    return np.stack([nx, ny, nz], axis=2), q


# ----------------------------------------------------------------------------------------------------------------
# whole scan


def prepare_scan(
    scan: Scan, cfg: PreprocessConfig | None = None, *, remove: bool = True, scanner: ScannerModel | None = None
) -> Prepared:
    """Outlier removal, normals toward the laser source, and per-point geometry for the finite points of a scan.

    Organized scans use the grid path when ``cfg.use_grid``; unorganized ones the open3d path. ``remove=False``
    keeps the outliers (their indices are still reported in ``outlier``). ``scanner`` None → the packaged default
    (its baseline gives the camera direction V). Raises PreprocessError on an empty / all-NaN cloud or when fewer
    than ``cfg.min_points`` points are left."""
    cfg = cfg or PreprocessConfig()
    scanner = scanner or ScannerModel.load()
    pts_all = np.asarray(scan.points)  # float32 from a ROS cloud or float64: kept as is, cast where needed
    flat = pts_all.reshape(-1, 3)
    if len(flat) == 0:
        raise PreprocessError("empty point cloud")
    grid = scan.organized and cfg.use_grid
    if not grid:
        valid = np.isfinite(flat).all(axis=1)
        if not valid.any():
            raise PreprocessError(f"no finite point in the cloud ({len(flat)} points, all NaN/inf)")
    if grid:
        h, w = scan.shape
        x, y, z, gvalid = _planes(pts_all)
        n_valid = int(np.count_nonzero(gvalid))
        if n_valid == 0:
            raise PreprocessError(f"no finite point in the cloud ({len(flat)} points, all NaN/inf)")
        out_mask = _grid_outliers_planes(x, y, z, gvalid, cfg.grid_min_offset_mm, cfg.grid_offset_factor,
                                         cfg.grid_gap_factor, cfg.grid_scale_window)
        outlier = np.flatnonzero(out_mask)
        if remove and outlier.size:
            for c in (x, y, z):
                c[out_mask] = np.nan
            gvalid &= ~out_mask
        index = np.flatnonzero(gvalid)
        if len(index) < cfg.min_points:
            raise PreprocessError(f"only {len(index)} points left after outlier removal (need {cfg.min_points})")
        nx, ny, nz, q, _ = _grid_normals_planes(x, y, z, gvalid, cfg.grid_window)
        normals = np.empty((len(index), 3), dtype=np.float32)
        for j, c in enumerate((nx, ny, nz)):
            normals[:, j] = c.reshape(-1)[index]
        quality = q.reshape(-1)[index]
        points = flat[index].astype(np.float64, copy=False)
    else:
        vidx = np.flatnonzero(valid)
        n_valid = len(vidx)
        keep = remove_outliers(flat[vidx], cfg.nb_neighbors, cfg.std_ratio)
        outlier = vidx[~keep]
        index = vidx[keep] if remove else vidx
        if len(index) < cfg.min_points:
            raise PreprocessError(f"only {len(index)} points left after outlier removal (need {cfg.min_points})")
        points = flat[index].astype(np.float64, copy=False)
        normals, quality = estimate_normals(points, radius_mm=cfg.normal_radius_mm, max_nn=cfg.max_nn, toward=None)
    geom = point_geometry(points, scan.pose, scanner.baseline_mm, dtype=np.float32)
    # Orient toward the laser source (outward on the lit side of a closed artifact); undefined normals → L, q = 0.
    normals = np.ascontiguousarray(normals, dtype=np.float32)
    bad = ~np.isfinite(normals).all(axis=1)
    if bad.any():
        normals[bad] = geom.L[bad]
        quality = quality.copy()
        quality[bad] = 0
    _orient(normals, points, geom.L)
    fields = {k: np.asarray(v).reshape(-1)[index] for k, v in scan.fields.items()}
    return Prepared(
        points=points,
        normals=normals,
        normal_quality=np.asarray(quality, dtype=np.float32),
        index=index,
        outlier=outlier,
        fields=fields,
        settings=scan.settings,
        pose=scan.pose,
        scanner=scanner,
        geometry=geom,
        shape=scan.shape,
        meta={"path": "grid" if grid else "open3d", "n_valid": n_valid},
    )
