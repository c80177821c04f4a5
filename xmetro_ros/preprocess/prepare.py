"""``prepare_scan``: outliers + oriented normals + per-point geometry of a whole scan."""

from __future__ import annotations

import numba
import numpy as np

from ..scan.geometry import point_geometry, point_geometry_posed
from ..scan.scan import Scan
from ..scan.scanner import ScannerModel
from .config import Prepared, PreprocessConfig, PreprocessError
from .grid import _grid_normals_planes, _grid_outliers_planes, _planes
from .knn import _knn_unorganized
from .normals import estimate_normals
from .open3d_ref import remove_outliers
from .points import _orient


def _prepare_grid_compiled(
    pts: np.ndarray, cfg: PreprocessConfig, remove: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """The grid path of :func:`prepare_scan` with the compiled kernels: (outlier flat indices,
    kept flat indices, kept points (M, 3) float64, their normals (M, 3) float32 (NaN: undefined, sign the grid's)
    and quality (M,), number of valid cells). Same rules and results as the numpy branch there."""
    from .grid_kernels import grid_outliers, kept_normals, planes

    x, y, z, gvalid, n_valid = planes(pts)
    if n_valid == 0:
        raise PreprocessError(f"no finite point in the cloud ({gvalid.size} points, all NaN/inf)")
    out_mask = grid_outliers(x, y, z, gvalid, cfg.grid_min_offset_mm, cfg.grid_offset_factor,
                             cfg.grid_gap_factor, cfg.grid_scale_window)
    outlier = np.flatnonzero(out_mask)
    if remove and outlier.size:
        for c in (x, y, z):
            c[out_mask] = np.nan
        gvalid &= ~out_mask
    n_kept = n_valid - outlier.size if remove else n_valid  # outliers are valid cells
    if n_kept < cfg.min_points:
        raise PreprocessError(f"only {n_kept} points left after outlier removal (need {cfg.min_points})")
    index, normals, quality, points = kept_normals(pts, x, y, z, gvalid, cfg.grid_window)
    return outlier, index, points, normals, quality, n_valid


def prepare_scan(
    scan: Scan, cfg: PreprocessConfig | None = None, *, remove: bool = True, scanner: ScannerModel | None = None
) -> Prepared:
    """Outlier removal, normals toward the laser source, and per-point geometry for the finite points of a scan.

    Organized scans use the grid path when ``cfg.use_grid``; unorganized ones ``cfg.unorganized_method`` ("knn",
    one shared kNN query, default; or "open3d", the reference); ``meta["path"]`` says which. ``remove=False``
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
    if grid and cfg.grid_backend == "numba":
        outlier, index, points, normals, quality, n_valid = _prepare_grid_compiled(pts_all, cfg, remove)
    elif grid:
        _h, _w = scan.shape
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
        if cfg.unorganized_method == "knn":  # one kNN query shared by the outlier removal and the normals
            keep, nk, qk = _knn_unorganized(flat[vidx], cfg.nb_neighbors, cfg.std_ratio, cfg.normal_radius_mm,
                                            cfg.knn_normal_neighbors, remove=remove,
                                            workers=cfg.knn_workers or numba.get_num_threads())
        else:
            keep = remove_outliers(flat[vidx], cfg.nb_neighbors, cfg.std_ratio)
        outlier = vidx[~keep]
        index = vidx[keep] if remove else vidx
        if len(index) < cfg.min_points:
            raise PreprocessError(f"only {len(index)} points left after outlier removal (need {cfg.min_points})")
        points = flat[index].astype(np.float64, copy=False)
        if cfg.unorganized_method == "knn":
            sel = keep if remove else slice(None)
            assert nk is not None and qk is not None  # the knn branch above computed them
            normals, quality = nk[sel], qk[sel]  # NaN (undefined) normals get L and quality 0 below
        else:
            normals, quality = estimate_normals(points, radius_mm=cfg.normal_radius_mm, max_nn=cfg.max_nn)
    if scan.row_poses is None:
        geom = point_geometry(points, scan.pose, scanner.camera_mm, dtype=np.float32)
    else:  # each point from the pose of the profile that measured it (a stream posed by /tf)
        rp = scan.row_poses
        geom = point_geometry_posed(points, rp.rows.reshape(-1)[index], rp, scanner.camera_mm, scan.pose,
                                    dtype=np.float32)
    # Orient toward the laser source (outward on the lit side of a closed artifact); undefined normals → L, q = 0.
    if grid and cfg.grid_backend == "numba":
        from .grid_kernels import orient_rows

        orient_rows(normals, quality, geom.L)  # the same two rules in one compiled pass
    else:
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
        meta={"path": "grid" if grid else cfg.unorganized_method, "n_valid": n_valid},
    )

