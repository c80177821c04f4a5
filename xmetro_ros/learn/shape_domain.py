"""The shapes a model set was calibrated on, as a range of the surface's mean curvature (card ``domain_shape``).

The per-point features carry no shape: a model trained on spheres and cylinders extrapolates silently to a concave
pocket or a sharp edge, and its intervals fail there first (docs/parts-generalisation.md). The judge therefore also
compares each point's mean curvature (:mod:`xmetro_ros.preprocess.curvature`) with the range the calibration clouds
covered — those clouds are the training campaign simulated again (same artifacts, settings and poses, new noise), so
their shapes are the training shapes. Points outside ``[lo − m, hi + m]`` (m = ``domain_margin`` × (hi − lo)) are
flagged OUT_OF_DOMAIN; U is not widened there (nothing says by how much), the flag says the interval is not vouched
for.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np

__all__ = ["SHAPE_QUANTILE", "fit_shape_domain", "shape_domain_of_scans"]

SHAPE_QUANTILE = 0.001  # as the multivariate domain: 0.1 % of the calibration points fall outside on each side


def fit_shape_domain(curvatures: Iterable[np.ndarray], quantile: float = SHAPE_QUANTILE) -> dict[str, Any]:
    """The card's ``domain_shape`` block from the mean curvatures (1/mm) of the calibration clouds' points (NaN
    ignored): ``{"measure", "radius_mm", "lo", "hi", "quantile", "n"}``. Raises ValueError without finite values."""
    from ..preprocess.curvature import RADIUS_MM

    c = np.concatenate([np.asarray(x, np.float64).reshape(-1) for x in curvatures] or [np.zeros(0)])
    c = c[np.isfinite(c)]
    if len(c) == 0:
        raise ValueError("no finite curvature: the shape domain needs organized calibration scans")
    return {"measure": "mean curvature 1/mm from normals 1 mm apart on the scan grid "
                       "(xmetro_ros.preprocess.curvature)",
            "radius_mm": RADIUS_MM, "lo": float(np.quantile(c, quantile)), "hi": float(np.quantile(c, 1 - quantile)),
            "quantile": float(quantile), "n": len(c),
            "rule": "a point whose curvature lies outside [lo - m, hi + m], m = domain_margin * (hi - lo), is "
                    "OUT_OF_DOMAIN (U not widened); unorganized scans are not checked"}


def shape_domain_of_scans(scans: Iterable[Any], scanner: Any = None, quantile: float = SHAPE_QUANTILE
                          ) -> dict[str, Any]:
    """:func:`fit_shape_domain` of simulated or measured organized scans, each pre-processed as the judge does."""
    from ..preprocess import prepare_scan
    from ..preprocess.curvature import mean_curvature

    return fit_shape_domain((mean_curvature(prepare_scan(s, scanner=scanner)) for s in scans), quantile)
