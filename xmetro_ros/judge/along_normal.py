"""d and U along the measured surface normal (card block ``uncertainty.along_normal``).

The model's target is a deviation from the nominal surface (the closest nominal point), so the true error of a point
lies along the surface normal; its X component is (error along the normal) × N_x. The per-axis d and U the model
gives carry X and Y errors it learnt on curved artifacts, also on faces where the true X and Y are ~0
(docs/parts-normal.md). A card with this block makes the judge publish instead, for each row with a measured noise:

- d' = (d·n)·n, n the judge's unit normal of the point (measured on the scan, the features N_x, N_y, N_z);
- U along the normal U_n = m·σ, σ the scan's own noise along the normal (:mod:`xmetro_ros.preprocess.noise`), m the
  split-conformal multiplier of the row's exposure level × surface class;
- U'_a = U_n·√(n_a² + θ_a²), θ_a = c_a·τ_a an allowance for the error of n's direction along axis a, τ_a the
  scan's own measured tilt noise of the point's normal on that axis (:mod:`xmetro_ros.preprocess.tilt_noise`,
  allowance model ``measured_tilt``), c_a split-conformal per incidence bin × surface class × axis × whether the
  axis carries the deviation (|n_a| ≥ :data:`CARRY`) (the bins of the card's U, :mod:`.conditions`).

Why: with the true normal N = n − δ, the residual on axis a is (a_n − d_n)·N_a − d_n·δ_a, a_n the true deviation
along N, d_n = d·n. Where the axis carries the deviation the first term dominates and U_n·|n_a| misses where δ_a
takes n_a below N_a; where it carries almost none (a cylinder's axis, a level face's X and Y) the residual is
d_n·δ_a, and a c shared with the carrying rows covered a cylinder's Y on 79 % (docs/along-normal.md). τ_a is read
from the scan because δ_a is not noise alone: near an edge the grid normals' window reaches across it.
0.9.1's blocks (``tangent_slopes``) took θ_a = c_a·σ·g_a, g_a (1/mm) how a plane fit's slope errors reach axis a
(:func:`tilt_gain`): the grid's two slopes, along the laser line (X, spacing h_x = 1/lateral density) and along the
scan (Y, h_y = 1/direction density), each err by ~ (σ/n_z)/h; a 0.9.0 block (``coarser_spacing``: no
``allowance_model`` key, one c per class) used g_a = √(1 − n_a²)/max(h_x, h_y). Both still read as calibrated.

A row without a measured noise or tilt noise (an unorganized scan, a hole's or the border's points), or of a class
or exposure level the calibration never had, keeps the model's d and U. Calibration:
:func:`xmetro_ros.learn.along_normal.fit`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numba import njit, prange

from ..compute import threads as _threads  # noqa: F401 - the threading layer, before any parallel kernel runs
from .conditions import INCIDENCE_EDGES_DEG, interior_edges

__all__ = ["ALLOWANCE_MODELS", "CARRY", "MEASURED_TILT", "AlongNormal", "AlongNormalRows", "allowance_scale",
           "axis_group", "exposure_level", "grid_spacings_mm", "incidence_bin", "tilt_gain", "warm_up"]

#: The allowance model that reads n's direction error from the scan itself (:func:`allowance_scale`).
MEASURED_TILT = "measured_tilt"
#: How the allowance for n's direction error reaches each axis (:func:`allowance_scale`): ``measured_tilt`` (since
#: 0.9.3, what :func:`xmetro_ros.learn.along_normal.fit` calibrates: the scan's measured tilt noise,
#: :mod:`xmetro_ros.preprocess.tilt_noise`), ``tangent_slopes`` (0.9.1's: σ·g from the grid spacings,
#: :func:`tilt_gain`) and ``coarser_spacing`` (0.9.0's).
ALLOWANCE_MODELS = (MEASURED_TILT, "tangent_slopes", "coarser_spacing")
#: |n_a| from which axis a counts as carrying the deviation (~3° from the plane perpendicular to the axis): the
#: allowance's second group index, 0 carrying, 1 not (``tools/normal_projection.py`` scores axes by the same cut).
CARRY = 0.05


def axis_group(normals: np.ndarray) -> np.ndarray:
    """(M, 3) int64: each axis's allowance group, 0 where it carries the deviation (|n_a| ≥ :data:`CARRY`), 1 where
    it does not. The one rule the judge and the calibration both take."""
    return (np.abs(np.asarray(normals, np.float64)) < CARRY).astype(np.int64)


def grid_spacings_mm(lateral_density: Any, direction_density: Any) -> np.ndarray:
    """(..., 2) mm: a scan's grid spacings along the laser line (X, 1/lateral density) and along the scan (Y,
    1/direction density) from its densities (points/mm); scalars or arrays of rows. The one definition the judge
    and the calibration (``learn/along_normal.py``) both take."""
    return np.stack(np.broadcast_arrays(1.0 / np.asarray(lateral_density, np.float64),
                                        1.0 / np.asarray(direction_density, np.float64)), axis=-1)


def tilt_gain(normals: np.ndarray, spacings_mm: np.ndarray, model: str = "tangent_slopes") -> np.ndarray:
    """g (M, 3) 1/mm: how much a slope error of the scan's plane fits, per mm of noise along the normal, moves each
    axis of the unit ``normals`` (M, 3) (sensor frame: X along the laser line, Y along the scan), for grid
    ``spacings_mm`` (2,) or (M, 2) (h_x, h_y). ``tangent_slopes``: n = (−p, −q, 1)/√(1 + p² + q²) of the height
    field z(x, y); its slopes p, q err by ~ (σ/n_z)/h_x and (σ/n_z)/h_y (the noise σ along n is σ/n_z along Z),
    independently, and ∂n/∂p = −n_z·(e_x − n_x·n), ∂n/∂q = −n_z·(e_y − n_y·n) give
    g_x = √((1 − n_x²)²/h_x² + n_x²n_y²/h_y²), g_y = √(n_x²n_y²/h_x² + (1 − n_y²)²/h_y²),
    g_z = |n_z|·√(n_x²/h_x² + n_y²/h_y²). ``coarser_spacing`` (0.9.0): g_a = √(1 − n_a²)/max(h_x, h_y)."""
    n = np.asarray(normals, np.float64)
    h = np.broadcast_to(np.asarray(spacings_mm, np.float64), (len(n), 2))
    if model == "coarser_spacing":
        return np.sqrt(np.maximum(1.0 - n**2, 0.0)) / h.max(axis=1)[:, None]
    if model != "tangent_slopes":
        raise ValueError(f"along_normal: unknown allowance model {model!r} (known: {', '.join(ALLOWANCE_MODELS)})")
    ax, ay = 1.0 / h[:, 0], 1.0 / h[:, 1]
    nx, ny, nz = n[:, 0], n[:, 1], n[:, 2]
    cross2 = (nx * ny) ** 2
    return np.stack([np.sqrt(((1.0 - nx**2) * ax) ** 2 + cross2 * ay**2),
                     np.sqrt(cross2 * ax**2 + ((1.0 - ny**2) * ay) ** 2),
                     np.abs(nz) * np.sqrt((nx * ax) ** 2 + (ny * ay) ** 2)], axis=1)


def allowance_scale(normals: np.ndarray, noise: np.ndarray, spacings_mm: Any, model: str,
                    tilt: np.ndarray | None = None) -> np.ndarray:
    """(M, 3) radians: the scale θ_a / c_a of the allowance for n's direction error on each axis, for rows with unit
    ``normals`` (M, 3), measured ``noise`` σ (M,) mm and grid ``spacings_mm``: ``measured_tilt`` the rows' measured
    tilt noise ``tilt`` (M, 3) (:mod:`xmetro_ros.preprocess.tilt_noise`; None: NaN, no allowance can be given); the
    grid models σ·g_a (:func:`tilt_gain`)."""
    n = np.asarray(normals, np.float64)
    if model == MEASURED_TILT:
        if tilt is None:
            return np.full(n.shape, np.nan)
        t = np.asarray(tilt, np.float64)
        if t.shape != n.shape:
            raise ValueError(f"along_normal: tilt noise {t.shape} for normals {n.shape}")
        return t
    sigma = np.asarray(noise, np.float64).reshape(-1)
    return sigma[:, None] * tilt_gain(n, spacings_mm, model)


def incidence_bin(incidence_edges_deg: Any, incidence: np.ndarray) -> np.ndarray:
    """(M,) int64: the incidence bin of rows with ``incidence`` (M,) the cos of their angle (the Inc feature), by
    the card's U's rule (:func:`.conditions.interior_edges`: the number of interior edges the angle reaches);
    NaN → bin 0 (callers mask such rows)."""
    cos_e, _ = interior_edges(incidence_edges_deg, [0.0, np.inf])
    inc = np.asarray(incidence, np.float64).reshape(-1)
    return (np.nan_to_num(inc, nan=2.0)[:, None] <= cos_e[None, :]).sum(axis=1).astype(np.int64)


def exposure_level(exposure_edges: np.ndarray, exposure_ms: Any) -> Any:
    """The exposure level of an exposure (ms; scalar or array): the number of ``exposure_edges`` at or below it.
    The one rule the judge and the calibration both take."""
    return np.searchsorted(exposure_edges, exposure_ms, side="right")


@dataclass(frozen=True)
class AlongNormal:
    """The calibrated block: ``exposure_edges`` (L − 1,) ms between the L exposure levels (a row's level: the number
    of edges below its exposure), ``multipliers`` (L, C) m per level × surface class (NaN: not calibrated),
    ``allowance`` (B, C, 3, 2) c per incidence bin × surface class × axis × (the axis carries the deviation,
    |n_a| ≥ :data:`CARRY`; it does not), the bins ``incidence_edges_deg`` (B + 1,) over acos(Inc) as the card's U
    has them (:mod:`.conditions`), or (C,) one c per class for every axis (0.9.0) (NaN: not calibrated),
    ``level`` the coverage they were calibrated for, ``allowance_model`` how c reaches each axis
    (:func:`tilt_gain`)."""

    exposure_edges: np.ndarray
    multipliers: np.ndarray
    allowance: np.ndarray
    level: float = 0.95
    allowance_model: str = "tangent_slopes"
    incidence_edges_deg: np.ndarray = field(default_factory=lambda: np.asarray(INCIDENCE_EDGES_DEG))

    def __post_init__(self) -> None:
        m, c = np.asarray(self.multipliers), np.asarray(self.allowance)
        bins = len(self.incidence_edges_deg) - 1
        if (m.ndim != 2 or m.shape[0] != len(self.exposure_edges) + 1
                or c.shape not in ((m.shape[1],), (bins, m.shape[1], 3, 2))):
            raise ValueError(f"along_normal: {m.shape} multipliers, {c.shape} allowances, "
                             f"{len(self.exposure_edges)} exposure edges and {bins} incidence bins do not match")
        if self.allowance_model not in ALLOWANCE_MODELS:
            raise ValueError(f"along_normal: unknown allowance model {self.allowance_model!r} "
                             f"(known: {', '.join(ALLOWANCE_MODELS)})")

    @classmethod
    def from_card(cls, card: dict[str, Any]) -> AlongNormal | None:
        """The card's ``uncertainty.along_normal`` block, None when it has none."""
        block = (card.get("uncertainty") or {}).get("along_normal")
        if not block:
            return None

        def arr(v: Any) -> np.ndarray:  # JSON null → NaN, at any depth
            return np.asarray(np.vectorize(lambda x: np.nan if x is None else x, otypes=[np.float64])(
                np.asarray(v, dtype=object)), np.float64)

        return cls(np.asarray(block["exposure_edges_ms"], np.float64), arr(block["multipliers"]),
                   arr(block["allowance"]), float(block.get("level", 0.95)),
                   str(block.get("allowance_model", "coarser_spacing")),
                   np.asarray(block.get("incidence_edges_deg", INCIDENCE_EDGES_DEG), np.float64))

    def to_block(self) -> dict[str, Any]:
        """The card block (JSON: NaN written as null)."""
        def py(a: np.ndarray) -> Any:
            return [py(x) for x in a] if np.ndim(a) else (None if not np.isfinite(a) else float(a))

        return {"exposure_edges_ms": [float(e) for e in self.exposure_edges], "multipliers": py(self.multipliers),
                "allowance": py(self.allowance), "level": self.level, "allowance_model": self.allowance_model,
                "incidence_edges_deg": [float(e) for e in self.incidence_edges_deg]}

    @property
    def needs_tilt(self) -> bool:
        """True when the allowance reads the scan's measured tilt noise (``measured_tilt``): :meth:`rows` then
        needs each row's (:mod:`xmetro_ros.preprocess.tilt_noise`)."""
        return self.allowance_model == MEASURED_TILT

    def rows(self, normals: np.ndarray, noise: np.ndarray, surface_class: np.ndarray, exposure_ms: float,
             spacings_mm: Any, widen: np.ndarray | None = None, incidence: np.ndarray | None = None,
             tilt: np.ndarray | None = None) -> AlongNormalRows:
        """What this block does to M rows: their unit ``normals`` (M, 3) (the features N_x, N_y, N_z), measured
        ``noise`` (M,) mm (NaN: none), surface classes (M,), the scan's exposure (ms), its grid spacings (h_x, h_y)
        mm (:func:`grid_spacings_mm`) and ``widen`` (M,) the factor the model's U took outside the multivariate
        domain (max(1, distance); None: 1), which U' takes too, ``incidence`` (M,) the rows' Inc feature (cos
        of the angle between normal and laser; for an allowance per incidence bin) and ``tilt`` (M, 3) their
        measured tilt noise (radians; the ``measured_tilt`` allowance: a row without one keeps its d and U)."""
        n = np.ascontiguousarray(normals, np.float64)
        k = len(n)
        sigma = np.ascontiguousarray(noise, np.float64).reshape(-1)
        # the grid models' gain is taken on the unit normal; the measured tilt needs only the rows' count
        unit = n if self.needs_tilt else n / np.linalg.norm(n, axis=1, keepdims=True)
        scale = allowance_scale(unit, sigma, spacings_mm, self.allowance_model, tilt)
        a = np.asarray(self.allowance, np.float64)
        if a.ndim == 1:  # 0.9.0: one c per class for every axis, one incidence bin
            a = np.broadcast_to(a[None, :, None, None], (1, len(a), 3, 2))
        cos_e = np.zeros(0)
        inc = np.zeros(0)
        if len(a) > 1:
            if incidence is None:
                raise ValueError("along_normal: the allowance is per incidence bin; the rows' Inc is needed")
            cos_e, _ = interior_edges(list(self.incidence_edges_deg), [0.0, np.inf])
            inc = np.ascontiguousarray(incidence, np.float64).reshape(-1)
        w = np.ones(0) if widen is None else np.ascontiguousarray(widen, np.float64).reshape(-1)
        level = int(exposure_level(self.exposure_edges, float(exposure_ms)))
        use, unit_out, U = np.empty(k, np.bool_), np.empty((k, 3)), np.empty((k, 3))
        _rows_kernel(n, sigma, np.ascontiguousarray(surface_class, np.int64).reshape(-1),
                     np.ascontiguousarray(self.multipliers[level], np.float64), np.ascontiguousarray(a),
                     np.ascontiguousarray(cos_e, np.float64), inc, np.ascontiguousarray(scale, np.float64), w, CARRY,
                     use, unit_out, U)
        return AlongNormalRows(use=use, normals=unit_out, U=U)

    def apply(self, d: np.ndarray, U: np.ndarray, normals: np.ndarray, noise: np.ndarray,
              surface_class: np.ndarray, exposure_ms: float, spacings_mm: Any,
              widen: np.ndarray | None = None, incidence: np.ndarray | None = None,
              tilt: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(d', U') (M, 3) mm for the rows with d, U (M, 3) mm and what :meth:`rows` takes; a row without a noise, a
        calibrated factor or a finite d and U keeps its d and U."""
        r = self.rows(normals, noise, surface_class, exposure_ms, spacings_mm, widen, incidence, tilt)
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
        if y.ndim == 2:  # one scan's rows: the judge's hot path, compiled
            out = np.empty_like(y)
            _carry_kernel(np.ascontiguousarray(y), self.use, self.normals, self.U, output == "error", out)
            return out
        use = self.use & np.isfinite(y).all(axis=-1)
        if output == "error":
            out = np.einsum("...ij,ij->...i", y, self.normals)[..., None] * self.normals
        else:
            out = np.broadcast_to(self.U, y.shape)
        return np.where(use[..., None], out, y)

    def take(self, rows: np.ndarray) -> AlongNormalRows:
        """These rows' subset ``rows`` (indices)."""
        return AlongNormalRows(self.use[rows], self.normals[rows], self.U[rows])


@njit(cache=True, nogil=True, parallel=True)
def _rows_kernel(n: np.ndarray, sigma: np.ndarray, cls: np.ndarray, mult: np.ndarray, allowance: np.ndarray,
                 cos_e: np.ndarray, inc: np.ndarray, scale: np.ndarray, widen: np.ndarray, carry: float,
                 use: np.ndarray, unit: np.ndarray, U: np.ndarray) -> None:  # pragma: no cover - compiled
    """:meth:`AlongNormal.rows` row by row in one pass (on the judge's hot path: ~36 ms of numpy passes for 166k
    rows): the unit normal, m of the row's class at the scan's exposure level (``mult`` (C,)), c of its incidence
    bin (``cos_e`` the interior edges' cosines, none: one bin), class and axis group from ``allowance`` (B, C, 3, 2),
    θ_a = c_a·scale_a, U'_a = m·σ·max(1, widen)·√(n_a² + θ_a²); rows without a finite σ > 0, class factor, scale or
    normal are not used (unit normal 0, U' NaN). Each row its own answer: the same bits at any thread count."""
    n_cls = mult.shape[0]
    for i in prange(n.shape[0]):
        nx, ny, nz = n[i, 0], n[i, 1], n[i, 2]
        norm = np.sqrt(nx * nx + ny * ny + nz * nz)
        nx, ny, nz = nx / norm, ny / norm, nz / norm
        k = cls[i]
        s = sigma[i]
        ok = k >= 0 and k < n_cls and np.isfinite(s) and s > 0 and np.isfinite(nx) and np.isfinite(ny) \
            and np.isfinite(nz)
        b = 0
        if ok and cos_e.shape[0] > 0:
            c_inc = inc[i]
            if not np.isfinite(c_inc):
                ok = False
            for e in range(cos_e.shape[0]):
                if c_inc <= cos_e[e]:
                    b += 1
        m = mult[k] if ok else np.nan
        ok = ok and np.isfinite(m)
        un = m * s
        if ok and widen.shape[0] > 0:
            w = widen[i]
            if np.isfinite(w) and w > 1.0:
                un = un * w
        comp = (nx, ny, nz)
        for a in range(3):
            if not ok:
                break
            na = comp[a]
            c = allowance[b, k, a, 1 if abs(na) < carry else 0]
            th = c * scale[i, a]
            if not np.isfinite(th):
                ok = False
                break
            U[i, a] = un * np.sqrt(na * na + th * th)
        use[i] = ok
        if ok:
            unit[i, 0], unit[i, 1], unit[i, 2] = nx, ny, nz
        else:
            unit[i, 0], unit[i, 1], unit[i, 2] = 0.0, 0.0, 0.0
            U[i, 0], U[i, 1], U[i, 2] = np.nan, np.nan, np.nan


@njit(cache=True, nogil=True, parallel=True)
def _carry_kernel(y: np.ndarray, use: np.ndarray, unit: np.ndarray, U: np.ndarray, error: bool,
                  out: np.ndarray) -> None:  # pragma: no cover - compiled
    """:meth:`AlongNormalRows.carry` of one scan's rows y (M, 3): on used rows with a finite y, (y·n)·n (``error``)
    or U'; the rest copied. Row by row: the same bits at any thread count."""
    for i in prange(y.shape[0]):
        y0, y1, y2 = y[i, 0], y[i, 1], y[i, 2]
        if use[i] and np.isfinite(y0) and np.isfinite(y1) and np.isfinite(y2):
            if error:
                dn = y0 * unit[i, 0] + y1 * unit[i, 1] + y2 * unit[i, 2]
                out[i, 0], out[i, 1], out[i, 2] = dn * unit[i, 0], dn * unit[i, 1], dn * unit[i, 2]
            else:
                out[i, 0], out[i, 1], out[i, 2] = U[i, 0], U[i, 1], U[i, 2]
        else:
            out[i, 0], out[i, 1], out[i, 2] = y0, y1, y2


def warm_up() -> None:
    """Compile (or load from numba's cache) this module's kernels on a few rows."""
    an = AlongNormal(np.zeros(0), np.full((1, 1), 2.0), np.full((9, 1, 3, 2), 0.5))
    r = an.rows(np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]]), np.full(2, 0.01), np.zeros(2, np.int64), 0.5,
                (0.1, 0.25), widen=np.ones(2), incidence=np.ones(2))
    r.carry(np.zeros((2, 3)), "error")
    r.carry(np.zeros((2, 3)), "uncertainty")
