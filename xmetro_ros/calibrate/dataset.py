"""Learning tables and the study's protocol splits.

``build_table`` prepares each scan once (outlier removal, normals), samples at most ``max_points_per_cloud`` of its
kept points (seeded), and computes for those only: features, targets (nominal − measured, from the PREPARED points
against the scan's artifact: radial on spheres, axial on cylinders), the oracle (the simulator's noise-free
``expected_error`` at those points, NaN when the scan has none), the oracle noise std (the simulator's
``noise_std``: with the oracle, the oracle 95 % interval oracle ± 1.96·oracle_std; NaN when unknown and at the
spurious returns the simulator injected) and the cloud id.

``study_split`` is the study's protocol: per cloud, 100 random training points and five test draws of 50 points,
each draw without replacement and disjoint from the training points (seeded). ``cloud_split`` leaves whole clouds
(by default whole configurations: all clouds sharing the settings) out.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..judge.features import FeatureContext, compute_features
from ..preprocess import PreprocessConfig, prepare_scan
from ..scan.scan import Scan
from ..scan.scanner import ScannerModel
from ..scan.targets import errors_with_fit

__all__ = ["DatasetError", "StudySplit", "Table", "TablePart", "assemble_table", "build_table", "cloud_split",
           "sample_rows", "scan_part", "study_split"]


class DatasetError(ValueError):
    """Inputs that cannot make a table or a split (no scans, a scan without artifact, too few points, ...)."""


@dataclass
class Table:
    """A learning table (one row per sampled point).

    Attributes:
        X: (M, F) float32 features, columns ``feature_names``.
        y: (M, 3) float64 targets nominal − measured per axis, mm.
        cloud_id: (M,) int32 index of the source scan in the list given to build_table.
        oracle: (M, 3) float64 expected (noise-free) error at the point, mm; NaN where unknown.
        feature_names: list of F names.
        point_index: (M,) flat index of the point in its scan's grid / list.
        clouds: one dict per scan: label, settings, artifact, n_valid, n_kept, n_outliers, meta subset.
        oracle_std: (M, 3) float64 true std of the random part of the error at the point, mm; NaN where unknown
            or the point is an injected outlier (None: a table built without it).
    """

    X: np.ndarray
    y: np.ndarray
    cloud_id: np.ndarray
    oracle: np.ndarray
    feature_names: list[str]
    point_index: np.ndarray
    clouds: list[dict[str, Any]] = field(default_factory=list)
    oracle_std: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.X)

    def rows(self, idx: np.ndarray) -> Table:
        """The table restricted to rows ``idx``."""
        return Table(self.X[idx], self.y[idx], self.cloud_id[idx], self.oracle[idx], list(self.feature_names),
                     self.point_index[idx], self.clouds,
                     None if self.oracle_std is None else self.oracle_std[idx])


@dataclass
class StudySplit:
    """Row indices (into the table, or into the concatenated clouds) of the study's protocol.

    Attributes:
        train: (n_clouds × n_train,) training rows.
        tests: n_draws arrays of (n_clouds × n_test,) test rows; each draw is disjoint from train.
    """

    train: np.ndarray
    tests: list[np.ndarray]


def _cloud_rows(table_or_sizes: Table | Sequence[int]) -> list[np.ndarray]:
    if isinstance(table_or_sizes, Table):
        cid = table_or_sizes.cloud_id
        order = np.argsort(cid, kind="stable")
        ids, starts = np.unique(cid[order], return_index=True)
        return np.split(order, starts[1:]) if len(ids) else []
    sizes = [int(s) for s in table_or_sizes]
    if any(s < 0 for s in sizes):
        raise DatasetError("cloud sizes must be non-negative")
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    return [np.arange(offsets[i], offsets[i + 1]) for i in range(len(sizes))]


def study_split(table_or_sizes: Table | Sequence[int], n_train: int = 100, n_test: int = 50, n_draws: int = 5,
                seed: int = 0) -> StudySplit:
    """The study's protocol: for each cloud, ``n_train`` random training rows and ``n_draws`` test draws of
    ``n_test`` rows, each draw without replacement and disjoint from the cloud's training rows (draws may share
    rows with each other, as independent draws do). A cloud with fewer than n_train + n_test rows → DatasetError.
    Input: a Table (rows grouped by cloud_id) or the point counts of the clouds (rows of their concatenation)."""
    groups = _cloud_rows(table_or_sizes)
    if not groups:
        raise DatasetError("no clouds to split")
    rng = np.random.default_rng(seed)
    train: list[np.ndarray] = []
    tests: list[list[np.ndarray]] = [[] for _ in range(n_draws)]
    for k, rows in enumerate(groups):
        if len(rows) < n_train + n_test:
            raise DatasetError(f"cloud {k} has {len(rows)} points, the protocol needs at least {n_train + n_test}")
        perm = rng.permutation(rows)
        train.append(perm[:n_train])
        rest = perm[n_train:]
        for d in range(n_draws):
            tests[d].append(rng.choice(rest, size=n_test, replace=False))
    return StudySplit(np.concatenate(train), [np.concatenate(t) for t in tests])


def cloud_split(table: Table, test_fraction: float = 0.25, seed: int = 0, groups: Sequence[Any] | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """(train_rows, test_rows) leaving whole groups of clouds out. ``groups``: one key per cloud (default: the
    cloud's settings label, i.e. leave configurations out). At least one group goes to each side."""
    if not 0 < test_fraction < 1:
        raise DatasetError(f"test_fraction must be in (0, 1), got {test_fraction}")
    n_clouds = len(table.clouds) if table.clouds else int(table.cloud_id.max()) + 1
    keys = list(groups) if groups is not None else [c.get("label", i) for i, c in enumerate(table.clouds)]
    if len(keys) != n_clouds:
        raise DatasetError(f"groups has {len(keys)} keys for {n_clouds} clouds")
    uniq = sorted(set(map(str, keys)))
    if len(uniq) < 2:
        raise DatasetError("need at least two groups of clouds to leave some out")
    rng = np.random.default_rng(seed)
    n_test = min(len(uniq) - 1, max(1, round(test_fraction * len(uniq))))
    test_keys = set(rng.choice(uniq, size=n_test, replace=False).tolist())
    test_cloud = np.array([str(k) in test_keys for k in keys])
    is_test = test_cloud[table.cloud_id]
    return np.flatnonzero(~is_test), np.flatnonzero(is_test)


def sample_rows(rng: np.random.Generator, n: int, max_points_per_cloud: int | None) -> np.ndarray | None:
    """The sorted rows of a prepared scan of ``n`` points kept by ``build_table`` (None: all), drawn from ``rng``
    (one generator over the scans in order: the draws depend only on the sequence of ``n``)."""
    if max_points_per_cloud is not None and n > max_points_per_cloud:
        return np.sort(rng.choice(n, size=int(max_points_per_cloud), replace=False))
    return None


@dataclass
class TablePart:
    """One scan's rows of a :class:`Table` (``build_table`` concatenates them in scan order)."""

    X: np.ndarray
    y: np.ndarray
    oracle: np.ndarray
    point_index: np.ndarray
    cloud: dict[str, Any]
    oracle_std: np.ndarray


def scan_part(scan: Scan, prep: Any, sel: np.ndarray | None, names: Sequence[str], fit_center: bool = False
              ) -> TablePart:
    """Features, targets, oracle and cloud record of one prepared scan restricted to rows ``sel``."""
    n = len(prep)  # kept points before sampling (the cloud record's n_kept)
    if sel is not None:
        prep = prep.subset(sel)
    X = compute_features(list(names), FeatureContext.from_prepared(prep))
    if scan.artifact is None:
        raise DatasetError("the scan has no artifact: targets need the nominal shape")
    y, used = errors_with_fit(prep.points, scan.artifact, fit_center)
    if scan.expected_error is not None:
        oracle = np.asarray(scan.expected_error, dtype=np.float64).reshape(-1, 3)[prep.index]
    else:
        oracle = np.full((len(prep), 3), np.nan)
    std = np.full((len(prep), 3), np.nan)
    if scan.noise_std is not None:
        std = np.asarray(scan.noise_std, dtype=np.float64).reshape(-1, 3)[prep.index]
        if scan.injected_outlier is not None:
            std[np.asarray(scan.injected_outlier).reshape(-1)[prep.index]] = np.nan
    meta = scan.meta or {}
    return TablePart(X, y, oracle, prep.index, {
        "label": scan.settings.label(),
        "settings": scan.settings.as_tuple(),
        "artifact": used.to_dict(),
        "n_valid": prep.meta.get("n_valid"),
        "n_kept": n,
        "n_outliers": len(prep.outlier),
        "config_index": meta.get("config_index"),
        "seed": meta.get("seed"),
    }, std)


def assemble_table(parts: Sequence[TablePart], names: Sequence[str]) -> Table:
    """The table of the scans' parts, in order (cloud ids 0..n-1)."""
    if not parts:
        raise DatasetError("no scans")
    return Table(
        X=np.concatenate([p.X for p in parts]),
        y=np.concatenate([p.y for p in parts]),
        cloud_id=np.concatenate([np.full(len(p.point_index), k, dtype=np.int32) for k, p in enumerate(parts)]),
        oracle=np.concatenate([p.oracle for p in parts]),
        feature_names=list(names),
        point_index=np.concatenate([p.point_index for p in parts]),
        clouds=[p.cloud for p in parts],
        oracle_std=np.concatenate([p.oracle_std for p in parts]),
    )


def build_table(scans: Sequence[Scan], feature_names: Sequence[str], preprocess_cfg: PreprocessConfig | None = None,
                *, max_points_per_cloud: int | None = 2000, seed: int = 0, fit_center: bool = False,
                scanner: ScannerModel | None = None) -> Table:
    """Features, targets, oracle and cloud ids for the scans (see module doc). Each scan must carry its
    ``artifact``; ``fit_center`` fits its position first (nominal radius fixed). ``max_points_per_cloud`` None →
    every kept point. Scans may be a lazy iterable of Scan objects (each is prepared once, then dropped).
    :mod:`xmetro_ros.calibrate.dataset_dask` builds the same table with the scans spread over Dask workers."""
    names = list(feature_names)
    if not names:
        raise DatasetError("no feature names")
    cfg = preprocess_cfg or PreprocessConfig()
    scanner = scanner or ScannerModel.load()
    rng = np.random.default_rng(seed)
    parts = []
    for k, scan in enumerate(scans):
        if scan.artifact is None:
            raise DatasetError(f"scan {k} has no artifact: targets need the nominal shape")
        prep = prepare_scan(scan, cfg, scanner=scanner)
        parts.append(scan_part(scan, prep, sample_rows(rng, len(prep), max_points_per_cloud), names, fit_center))
    return assemble_table(parts, names)
