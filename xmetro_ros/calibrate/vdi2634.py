"""Acceptance figures of an optical 3D scanner on certified spheres, in the manner of VDI/VDE 2634-2 and
ISO 10360-8 (probing form, probing size, sphere spacing). Lengths in mm, in the scan frame.

- probing form error ``PF``: range (max − min) of the radial residuals of a least-squares sphere with a free
  radius, over the points assigned to the sphere less the 0.3 % with the largest residuals (the guideline allows
  that share to be discarded as outliers; ``outlier_fraction``);
- probing size error ``PS``: fitted diameter (free radius) − certified diameter;
- sphere spacing error ``SD``: distance between the fitted centres of two spheres − their calibrated distance
  (a ball bar), or, with a known (independently measured) position, fitted centre − known centre (its norm).

The guideline's figures are maxima over measurements of a configuration: :func:`summarize` gives per settings the
largest |PF|, |PS| and |SD| and how many measurements they come from.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..scan.fitting import fit_sphere

__all__ = ["SphereFigures", "probing", "spacing_error", "summarize"]


@dataclass(frozen=True)
class SphereFigures:
    """One sphere in one measurement: free fit and the guideline's figures (mm)."""

    center: tuple[float, float, float]
    diameter_mm: float
    form_error_mm: float  # PF
    size_error_mm: float  # PS
    rms_mm: float
    n_points: int
    location_error_mm: float | None = None  # |fitted − known centre| when the position is known

    def to_dict(self) -> dict[str, Any]:
        """JSON-able figures."""
        return {"center_mm": list(self.center), "diameter_mm": self.diameter_mm, "PF_mm": self.form_error_mm,
                "PS_mm": self.size_error_mm, "rms_mm": self.rms_mm, "n_points": self.n_points,
                "location_error_mm": self.location_error_mm}


def probing(points: np.ndarray, certified_diameter_mm: float, known_center: Iterable[float] | None = None,
            outlier_fraction: float = 0.003) -> SphereFigures:
    """PF and PS of one sphere from its measured points (N, 3) mm (free-radius least-squares fit, refitted
    without the ``outlier_fraction`` of points with the largest |residual|)."""
    p = np.asarray(points, dtype=float)
    p = p[np.isfinite(p).all(axis=1)]
    if len(p) < 10:
        raise ValueError(f"{len(p)} points: too few for a sphere fit (at least 10)")
    c, r, rms = fit_sphere(p)
    drop = int(np.floor(outlier_fraction * len(p)))
    if drop:
        res0 = np.abs(np.linalg.norm(p - c, axis=1) - r)
        p = p[np.argsort(res0)[: len(p) - drop]]
        c, r, rms = fit_sphere(p)
    res = np.linalg.norm(p - c, axis=1) - r
    loc = None if known_center is None else float(np.linalg.norm(c - np.asarray(list(known_center), dtype=float)))
    return SphereFigures((float(c[0]), float(c[1]), float(c[2])), float(2 * r), float(res.max() - res.min()),
                         float(2 * r - certified_diameter_mm), float(rms), len(p), loc)


def spacing_error(a: SphereFigures, b: SphereFigures, calibrated_distance_mm: float) -> float:
    """SD: measured centre distance of two spheres − their calibrated distance (mm)."""
    return float(np.linalg.norm(np.subtract(a.center, b.center)) - calibrated_distance_mm)


def summarize(rows: Iterable[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per settings label: max |PF|, |PS|, |SD| (mm) and the number of measurements behind each.

    ``rows``: dicts with ``settings`` (a label) and any of ``PF_mm``, ``PS_mm``, ``SD_mm``."""
    acc: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    for r in rows:
        for k in ("PF_mm", "PS_mm", "SD_mm", "location_error_mm"):
            v = r.get(k)
            if v is not None and np.isfinite(v):
                acc[str(r["settings"])][k].append(abs(float(v)))
    return {s: {k: {"max_abs": max(v), "n": len(v)} for k, v in d.items()} for s, d in sorted(acc.items())}
