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

__all__ = ["AlongNormal", "AlongNormalRows", "exposure_level", "grid_spacing_mm"]


def grid_spacing_mm(lateral_density: Any, direction_density: Any) -> Any:
    """h (mm): the coarser of a scan's two grid spacings from its densities (points/mm); scalars or arrays of rows.
    The one definition the judge and the calibration (``learn/along_normal.py``) both take."""
    return 1.0 / np.minimum(lateral_density, direction_density)


def exposure_level(exposure_edges: np.ndarray, exposure_ms: Any) -> Any:
    """The exposure level of an exposure (ms; scalar or array): the number of ``exposure_edges`` at or below it.
    The one rule the judge and the calibration both take."""
    return np.searchsorted(exposure_edges, exposure_ms, side="right")


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
        level = int(exposure_level(self.exposure_edges, float(exposure_ms)))
        ok = (cls >= 0) & (cls < self.multipliers.shape[1])
        k = np.where(ok, cls, 0)
        return (np.where(ok, self.multipliers[level, k], np.nan), np.where(ok, self.allowance[k], np.nan))

    def rows(self, normals: np.ndarray, noise: np.ndarray, surface_class: np.ndarray, exposure_ms: float,
             spacing_mm: float, widen: np.ndarray | None = None) -> AlongNormalRows:
        """What this block does to M rows: their unit ``normals`` (M, 3) (the features N_x, N_y, N_z), measured
        ``noise`` (M,) mm (NaN: none), surface classes (M,), the scan's exposure (ms), its coarser grid spacing (mm)
        and ``widen`` (M,) the factor the model's U took outside the multivariate domain (max(1, distance);
        None: 1), which U' takes too."""
        n = np.asarray(normals, np.float64)
        n = n / np.linalg.norm(n, axis=1, keepdims=True)
        sigma = np.asarray(noise, np.float64).reshape(-1)
        m, c = self.factors(surface_class, exposure_ms)
        use = np.isfinite(sigma) & (sigma > 0) & np.isfinite(m) & np.isfinite(c) & np.isfinite(n).all(axis=1)
        theta = c * sigma / float(spacing_mm)
        un = m * sigma
        if widen is not None:
            w = np.asarray(widen, np.float64).reshape(-1)
            un = un * np.where(np.isfinite(w), np.maximum(w, 1.0), 1.0)
        U = un[:, None] * np.sqrt(n**2 + (theta**2)[:, None] * (1.0 - n**2))
        return AlongNormalRows(use=use, normals=np.where(use[:, None], n, 0.0), U=np.where(use[:, None], U, np.nan))

    def apply(self, d: np.ndarray, U: np.ndarray, normals: np.ndarray, noise: np.ndarray,
              surface_class: np.ndarray, exposure_ms: float, spacing_mm: float,
              widen: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(d', U') (M, 3) mm for the rows with d, U (M, 3) mm and what :meth:`rows` takes; a row without a noise, a
        calibrated factor or a finite d and U keeps its d and U."""
        r = self.rows(normals, noise, surface_class, exposure_ms, spacing_mm, widen)
        return r.carry(d, "error"), r.carry(U, "uncertainty")


@dataclass(frozen=True)
class AlongNormalRows:
    """The block applied to M rows: ``use`` (M,) bool the rows it changes, ``normals`` (M, 3) their unit normals,
    ``U`` (M, 3) mm their U' (NaN where not used). The judge and the explainer carry outputs with the same rows."""

    use: np.ndarray
    normals: np.ndarray
    U: np.ndarray

    def carry(self, y: np.ndarray, output: str) -> np.ndarray:
        """Outputs y (..., M, 3) mm of these rows as published: "error" → (y·n)·n, "uncertainty" → U' on the used
        rows whose y is finite; the rest unchanged."""
        y = np.asarray(y, np.float64)
        use = self.use & np.isfinite(y).all(axis=-1)
        if output == "error":
            out = np.einsum("...ij,ij->...i", y, self.normals)[..., None] * self.normals
        else:
            out = np.broadcast_to(self.U, y.shape)
        return np.where(use[..., None], out, y)

    def take(self, rows: np.ndarray) -> AlongNormalRows:
        """These rows' subset ``rows`` (indices)."""
        return AlongNormalRows(self.use[rows], self.normals[rows], self.U[rows])
