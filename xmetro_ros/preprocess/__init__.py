"""Pre-processing of a scan (the study's §3.3): outlier removal and surface normals, oriented consistently.

Two paths:

- **Organized grid** (H profiles × W points, the virtual and live scanners): fully vectorised on the grid, float32.
  Outliers are points far from the chord of their two grid neighbours in *both* grid directions (a spurious
  return is off along its profile and its column; its neighbours only along one), relative to a local noise
  scale, plus points with no valid 4-neighbour within ``grid_gap_factor`` median spacings. Raw normals are the
  cross product of the column and row tangents (NaN-aware central differences); the normal is the normalised
  mean of the raw unit normals over a ``grid_window`` × ``grid_window`` box (a plane-fit-like average) and the
  quality is the length of that mean (1 = full, planar, noise-free window; lower near holes, edges, noise).
- **Unorganized** (N × 3), after removing exact duplicate points (real bags hold many; they break the neighbour
  statistics and make KD-trees slow). Two selectable methods (``PreprocessConfig.unorganized_method``):
  ``"knn"`` (default, the live path): ONE exact k-nearest-neighbour query (a compiled, parallel grid search,
  :mod:`.knn_grid`) feeds both steps: statistical outlier removal exactly as open3d defines it, then normals from
  the covariance of the kept points among the same neighbours (within ``normal_radius_mm``), smallest eigenvector by
  a closed-form 3×3 symmetric solver; quality = planarity 1 − λ0/λ1 (eigenvalues ascending).
  ``"open3d"`` (the reference, as in the study): open3d statistical outlier removal and KD-tree normal estimation
  (hybrid radius / max_nn); quality = 1 − nearest-neighbour distance / radius (clipped to [0, 1]).

Orientation: normals are flipped to have a positive dot product with ``toward`` (per point, e.g. toward the laser
source, which is outward for the visible side of a closed artifact); without ``toward``, away from the centroid.
Lengths in mm, scan frame. See docs/features.md for the agreement between the two paths.

Modules (one job each): :mod:`.config` (parameters, ``Prepared``, errors), :mod:`.points` (shared helpers),
:mod:`.grid` (organized path, numpy reference) and :mod:`.grid_kernels` (the same compiled), :mod:`.knn` and
:mod:`.open3d_ref` (unorganized methods), :mod:`.normals` (``estimate_normals`` dispatcher), :mod:`.prepare`
(``prepare_scan``).

May import: scan, compute.
"""

from .config import GRID_BACKENDS, UNORGANIZED_METHODS, Prepared, PreprocessConfig, PreprocessError
from .grid import grid_normals, grid_outliers, normals_grid
from .knn import normals_knn
from .normals import estimate_normals
from .open3d_ref import normals_open3d, remove_outliers
from .points import dedupe
from .prepare import prepare_scan

__all__ = [
    "GRID_BACKENDS",
    "UNORGANIZED_METHODS",
    "Prepared",
    "PreprocessConfig",
    "PreprocessError",
    "dedupe",
    "estimate_normals",
    "grid_normals",
    "grid_outliers",
    "normals_grid",
    "normals_knn",
    "normals_open3d",
    "prepare_scan",
    "remove_outliers",
]
