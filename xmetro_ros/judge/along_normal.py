"""d and U along the measured surface normal (card block ``uncertainty.along_normal``).

The model's target is a deviation from the nominal surface (the closest nominal point), so the true error of a point
lies along the surface normal; its X component is (error along the normal) × N_x. The per-axis d and U the model
gives carry X and Y errors it learnt on curved artifacts, also on faces where the true X and Y are ~0
(docs/parts-normal.md). A card with this block makes the judge publish instead, for each row with a measured noise:

- d' = (d·n)·n, n the judge's unit normal of the point (measured on the scan, the features N_x, N_y, N_z);
- U along the normal U_n = m·σ, σ the scan's own noise along the normal (:mod:`xmetro_ros.preprocess.noise`), m the
  split-conformal multiplier of the row's exposure level × surface class;
- U'_a = U_n·√(n_a² + θ²·(1 − n_a²)), θ = c·σ/h an allowance for the error of n's direction (σ/h: the scale of a
  plane fit's slope error, h the scan's coarser grid spacing in mm), c split-conformal per surface class.

A row without a measured noise (an unorganized scan, a hole's or the border's points), or of a class or exposure
level the calibration never had, keeps the model's d and U. Calibration: :func:`xmetro_ros.learn.along_normal.fit`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["AlongNormal"]


@dataclass(frozen=True)
class AlongNormal:
    """The calibrated block: ``exposure_edges`` (L − 1,) ms between the L exposure levels (a row's level: the number
    of edges below its exposure), ``multipliers`` (L, C) m per level × surface class (NaN: not calibrated),
    ``allowance`` (C,) c per surface class (NaN: not calibrated), ``level`` the coverage they were calibrated for."""

    exposure_edges: np.ndarray
    multipliers: np.ndarray
    allowance: np.ndarray
    level: float = 0.95

    def __post_init__(self) -> None:
        m, c = np.asarray(self.multipliers), np.asarray(self.allowance)
        if m.ndim != 2 or m.shape[0] != len(self.exposure_edges) + 1 or c.shape != (m.shape[1],):
            raise ValueError(f"along_normal: {m.shape} multipliers, {c.shape} allowances and "
                             f"{len(self.exposure_edges)} exposure edges do not match")

    @classmethod
    def from_card(cls, card: dict[str, Any]) -> AlongNormal | None:
        """The card's ``uncertainty.along_normal`` block, None when it has none."""
        block = (card.get("uncertainty") or {}).get("along_normal")
        if not block:
            return None
        nan = float("nan")
        return cls(np.asarray(block["exposure_edges_ms"], np.float64),
                   np.array([[nan if v is None else v for v in row] for row in block["multipliers"]], np.float64),
                   np.array([nan if v is None else v for v in block["allowance"]], np.float64),
                   float(block.get("level", 0.95)))

    def to_block(self) -> dict[str, Any]:
        """The card block (JSON: NaN written as null)."""
        def py(a: np.ndarray) -> Any:
            return [py(x) for x in a] if np.ndim(a) else (None if not np.isfinite(a) else float(a))

        return {"exposure_edges_ms": [float(e) for e in self.exposure_edges], "multipliers": py(self.multipliers),
                "allowance": py(self.allowance), "level": self.level}

    def factors(self, surface_class: np.ndarray, exposure_ms: float) -> tuple[np.ndarray, np.ndarray]:
        """(m (M,), c (M,)) of rows of the given surface classes (−1: none → NaN) at one exposure (ms)."""
        cls = np.asarray(surface_class, np.int64).reshape(-1)
        level = int(np.searchsorted(self.exposure_edges, float(exposure_ms), side="right"))
        ok = (cls >= 0) & (cls < self.multipliers.shape[1])
        k = np.where(ok, cls, 0)
        return (np.where(ok, self.multipliers[level, k], np.nan), np.where(ok, self.allowance[k], np.nan))

    def apply(self, d: np.ndarray, U: np.ndarray, normals: np.ndarray, noise: np.ndarray,
              surface_class: np.ndarray, exposure_ms: float, spacing_mm: float) -> tuple[np.ndarray, np.ndarray]:
        """(d', U') (M, 3) mm for the rows with d, U (M, 3) mm, their unit ``normals`` (M, 3), measured ``noise``
        (M,) mm (NaN: none), surface classes (M,), the scan's exposure (ms) and coarser grid spacing (mm); a row
        without a noise, a calibrated factor or a finite d and U keeps its d and U."""
        d = np.asarray(d, np.float64)
        U = np.asarray(U, np.float64)
        n = np.asarray(normals, np.float64)
        n = n / np.linalg.norm(n, axis=1, keepdims=True)
        sigma = np.asarray(noise, np.float64).reshape(-1)
        m, c = self.factors(surface_class, exposure_ms)
        use = (np.isfinite(sigma) & (sigma > 0) & np.isfinite(m) & np.isfinite(c) & np.isfinite(n).all(axis=1)
               & np.isfinite(d).all(axis=1) & np.isfinite(U).all(axis=1))
        un = m * sigma
        theta = c * sigma / float(spacing_mm)
        w = np.sqrt(n**2 + (theta**2)[:, None] * (1.0 - n**2))
        dn = np.einsum("ij,ij->i", d, n)
        d_out = np.where(use[:, None], dn[:, None] * n, d)
        U_out = np.where(use[:, None], un[:, None] * w, U)
        return d_out, U_out
