"""What a profilometer known only from its data does not say, measured on its calibration table: where the laser
fan starts and where the camera looks from. Each candidate geometry adds one feature to the profile model's and
is scored by the held-out MAE of d (folds of positions, no repeat of a held-out position in training); a flat
score over the candidates says the data cannot tell them apart, and that the choice costs nothing measurable.

- fan origin at height ``z_f`` on the sensor axis (the range coordinate's units; ``None`` = parallel rays, the
  product's default): the signed in-plane incidence between the arc normal and the direction to the origin;
- camera in the plane of the sensor axis and the scan direction (y), at ``gamma`` degrees from the axis (sign:
  toward +y): the viewing angle between the sphere's 3-D normal (its y component from the certified radius, the
  arc radius and the side of the recording: known on the calibration sphere only) and the camera direction.

Lengths mm, angles deg.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..calibrate.profile_table import ProfileTable
from .profile_model import ProfileModel

__all__ = ["fan_incidence", "geometry_sweep", "view_angle"]


def fan_incidence(table: ProfileTable, z_origin: float | None) -> np.ndarray:
    """(M,) signed in-plane angle (deg) between the arc normal and the direction to a fan origin at (0, z_origin)
    (``None``: the sensor axis, parallel rays)."""
    tw = table.toward[table.profile].astype(np.float64) if table.toward is not None else np.ones(len(table))
    if z_origin is None:
        return table.angle.copy()
    s = np.column_stack([-table.xz[:, 0], z_origin - table.xz[:, 1]])
    a_src = np.degrees(np.arctan2(s[:, 0], tw * s[:, 1]))
    return table.angle - a_src


def view_angle(table: ProfileTable, gamma_deg: float) -> np.ndarray:
    """(M,) angle (deg) between the sphere's outward 3-D normal and a camera direction tilted ``gamma_deg`` from
    the sensor axis toward +y."""
    R = table.radius
    r = table.arc_radius[table.profile]
    y0 = table.sides[table.profile].astype(np.float64) * np.sqrt(np.clip(R * R - r * r, 0.0, None))
    s = r / R  # the in-plane normal scaled to the 3-D unit normal
    n = np.column_stack([table.normals[:, 0] * s, -y0 / R, table.normals[:, 1] * s])
    tw = table.toward[table.profile].astype(np.float64) if table.toward is not None else np.ones(len(table))
    g = np.radians(gamma_deg)
    v = np.column_stack([np.zeros(len(n)), np.full(len(n), np.sin(g)), tw * np.cos(g)])
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", n, v), -1.0, 1.0)))


def _cv_mae(X: np.ndarray, y: np.ndarray, pos: np.ndarray, folds: int, iterations: int, seed: int) -> float:
    upos = np.unique(pos)
    fold_of = dict(zip(upos.tolist(), np.random.default_rng(seed).permutation(len(upos)) % folds, strict=False))
    f = np.array([fold_of[p] for p in pos.tolist()])
    err = np.empty(len(y))
    for k in range(folds):
        m = ProfileModel(iterations=iterations, seed=seed).fit_regressor(X[f != k], y[f != k])
        err[f == k] = np.abs(y[f == k] - m.predict(X[f == k]))
    return float(np.mean(err)) * 1000.0


def geometry_sweep(table: ProfileTable, rows: np.ndarray, *, fan_origins: list[float | None],
                   camera_gammas: list[float], folds: int = 2, iterations: int = 300, seed: int = 0
                   ) -> dict[str, Any]:
    """Held-out MAE (µm, target: the measured deviation) of the profile model on ``rows`` for each fan origin
    (inc_plane replaced) and each camera direction (view angle added), plus the model without either."""
    pos = table.position_ids()[rows]
    y = table.deviation[rows]
    X0 = table.X[rows]
    inc_col = table.feature_names.index("inc_plane")
    out: dict[str, Any] = {"rows": int(rows.sum()), "positions": len(np.unique(pos)), "folds": folds,
                           "iterations": iterations, "fan_origin": [], "camera": []}
    base = _cv_mae(X0, y, pos, folds, iterations, seed)
    out["profile_features_mae_um"] = base
    for zf in fan_origins:
        X = X0.copy()
        X[:, inc_col] = fan_incidence(table, zf)[rows]
        out["fan_origin"].append({"z_origin_mm": zf, "mae_um": _cv_mae(X, y, pos, folds, iterations, seed)})
    for g in camera_gammas:
        X = np.column_stack([X0, view_angle(table, g)[rows]]).astype(np.float32)
        out["camera"].append({"gamma_deg": g, "mae_um": _cv_mae(X, y, pos, folds, iterations, seed)})
    return out
