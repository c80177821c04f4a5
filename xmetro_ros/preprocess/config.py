"""Pre-processing parameters, the prepared scan and the error type (lengths in mm, scan frame)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..scan.geometry import HeadPose, PointGeometry
from ..scan.scanner import ScannerModel, ScanSettings

UNORGANIZED_METHODS = ("knn", "open3d")
# Organized-grid implementations: "numba" (compiled kernels, xmetro_ros.preprocess.grid_kernels; default) and
# "numpy" (the reference they are tested bit-identical against).
GRID_BACKENDS = ("numba", "numpy")


class PreprocessError(ValueError):
    """A cloud that cannot be pre-processed (empty, wrong shape, no finite point, too few points left)."""


@dataclass(frozen=True)
class PreprocessConfig:
    """Pre-processing parameters (lengths in mm).

    Attributes:
        nb_neighbors, std_ratio: statistical outlier removal (unorganized path, open3d's definition).
        normal_radius_mm, max_nn: hybrid radius / neighbour count for normals (unorganized path; max_nn is used by the
            open3d method).
        unorganized_method: ``"knn"`` (one shared kNN query, fast; default) or ``"open3d"`` (the reference).
        knn_normal_neighbors: the knn method's neighbours per normal (the query's k is max(nb_neighbors, this));
            20 rather than 30 makes the path 10-25 % cheaper at a normal accuracy inside the stated bounds.
        knn_workers: threads for the kNN query; 0 (default): the calling thread's numba thread count, i.e. the
            judge's thread budget (xmetro_ros.compute.threads).
        use_grid: use the organized-grid path when the scan is organized.
        grid_backend: ``"numba"`` (compiled kernels, default) or ``"numpy"``: the same rules with bit-identical
            outlier masks, normals and quality (see xmetro_ros.preprocess.grid_kernels); numpy is kept as the reference.
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
    unorganized_method: str = "knn"
    knn_normal_neighbors: int = 20
    knn_workers: int = 0
    use_grid: bool = True
    grid_backend: str = "numba"
    grid_window: int = 5
    grid_min_offset_mm: float = 0.05
    grid_offset_factor: float = 6.0
    grid_scale_window: int = 9
    grid_gap_factor: float = 20.0
    min_points: int = 3

    def __post_init__(self) -> None:
        if self.unorganized_method not in UNORGANIZED_METHODS:
            raise PreprocessError(f"unorganized_method must be one of {UNORGANIZED_METHODS}, "
                                  f"got {self.unorganized_method!r}")
        if self.grid_backend not in GRID_BACKENDS:
            raise PreprocessError(f"grid_backend must be one of {GRID_BACKENDS}, got {self.grid_backend!r}")
        if self.knn_normal_neighbors < 3 or self.knn_workers < 0:
            raise PreprocessError(f"knn_normal_neighbors must be >= 3 and knn_workers >= 0, got "
                                  f"{self.knn_normal_neighbors}, {self.knn_workers}")


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


