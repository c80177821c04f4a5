"""The calibration clouds of a model set, read once: the rows for the conformal scores (a learning table, each row
with its surface class) and the shapes of every kept point (for the shape domain).

Each scan is pre-processed once, as the judge does (:func:`xmetro_ros.preprocess.prepare_scan`); its kept points
give the mean curvature and the principal curvatures (:mod:`xmetro_ros.preprocess.curvature`) for the card's
``domain_shape``, and a sample of them (``build_table``'s draw: the same rows for the same scans and seed) the
calibration rows, whose surface classes (:mod:`xmetro_ros.judge.surface_class`) and measured noise
(:mod:`xmetro_ros.preprocess.noise`, computed on the whole scan as the judge does) the per-class multipliers need,
and whose measured tilt noise (:mod:`xmetro_ros.preprocess.tilt_noise`, likewise) the along-normal block's.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["CalibrationSet", "calibration_set"]


@dataclass
class CalibrationSet:
    """Calibration rows and shapes.

    Attributes:
        table: the learning table of the sampled rows (features, targets mm, cloud ids, …).
        kappa: (M, 2) principal curvatures (κmin, κmax) 1/mm of the table's rows (NaN: none).
        surface_class: (M,) int8 class of each row (−1: none).
        noise: (M,) float64 measured noise (mm, along the normal) of each row (NaN: none).
        tilt: (M, 3) float64 measured tilt noise (radians, per component of the normal) of each row (NaN: none).
        mean_curvature: per scan, the mean curvature (1/mm) of every kept point, float32.
        principal: per scan, the principal curvatures (N, 2) of every kept point, float32.
    """

    table: Any
    kappa: np.ndarray
    surface_class: np.ndarray
    noise: np.ndarray
    mean_curvature: list[np.ndarray]
    principal: list[np.ndarray]
    tilt: np.ndarray


def calibration_set(scans: Iterable[Any], feature_names: Sequence[str], *, max_points_per_cloud: int | None,
                    seed: int, scanner: Any = None) -> CalibrationSet:
    """The :class:`CalibrationSet` of the scans (each must carry its ``artifact``; a lazy iterable is read once)."""
    from ..calibrate.dataset import DatasetError, assemble_table, sample_rows, scan_part
    from ..judge.surface_class import surface_class
    from ..preprocess import PreprocessConfig, prepare_scan
    from ..preprocess.curvature import mean_curvature, principal_curvatures
    from ..preprocess.noise import noise_scale
    from ..preprocess.tilt_noise import tilt_noise
    from ..scan.scanner import ScannerModel

    names = list(feature_names)
    cfg = PreprocessConfig()
    scanner = scanner or ScannerModel.load()
    rng = np.random.default_rng(seed)
    parts, kap, mean, princ, noise, tilt = [], [], [], [], [], []
    for k, scan in enumerate(scans):
        if scan.artifact is None:
            raise DatasetError(f"scan {k} has no artifact: targets need the nominal shape")
        prep = prepare_scan(scan, cfg, scanner=scanner)
        sel = sample_rows(rng, len(prep), max_points_per_cloud)
        pk = principal_curvatures(prep)
        mean.append(mean_curvature(prep).astype(np.float32))
        princ.append(pk.astype(np.float32))
        kap.append(pk if sel is None else pk[sel])
        nz = noise_scale(prep)  # on the whole scan, before the rows are drawn (its windows need the neighbours)
        noise.append(nz if sel is None else nz[sel])
        tz = tilt_noise(prep, offset=cfg.grid_window)
        tilt.append(tz if sel is None else tz[sel])
        parts.append(scan_part(scan, prep, sel, names))
    table = assemble_table(parts, names)
    kappa = np.concatenate(kap) if kap else np.zeros((0, 2))
    return CalibrationSet(table, kappa, surface_class(kappa), np.concatenate(noise) if noise else np.zeros(0),
                          mean, princ, np.concatenate(tilt) if tilt else np.zeros((0, 3)))
