"""The per-point table of a profile calibration: single profiles of a certified sphere → arc points with their
measured deviation, the features the profile model sees, and the repeat statistics (systematic / random).

Per profile (sensor frame, mm): the product's own segmentation (:func:`~xmetro_ros.preprocess.profile_arc.
segment_sphere_arc`, no labels) finds and fits the arc of the sphere; the arc's circle is the nominal surface in
the laser plane (its centre and radius r are fitted per profile: a sphere's plane section has r = sqrt(R² − y0²)
for the certified R and the unknown out-of-plane offset y0, whose sign the recording gives). Per point:

- ``deviation`` = nominal − measured along the arc's outward normal (mm; the study's target sign, eq. 8-15;
  published values carry its negative, docs/conventions.md): −(|p − c| − r); per axis ``errors`` = deviation ×
  (n_x, 0, n_z) — y carries no error, a profile point lies in the laser plane by construction;
- features (``PROFILE_FEATURES``), computable from the profile alone: ``u`` the position along the laser line
  (x, mm), ``w`` the range coordinate (z, mm), ``inc_plane`` the signed in-plane angle between the surface
  normal and the sensor axis (deg; the laser fan's origin and the camera are unknown for a profilometer known
  only from its data, see docs/real-data.md), ``arc_curvature`` 1/r of the profile's arc (1/mm);
- repeat statistics over the profiles of the same position (the repeats, interpolated along x, never across a
  gap wider than ``MAX_GAP_MM``): ``systematic`` the mean deviation, ``spread`` the standard deviation between
  repeats, ``n_repeats`` how many repeats cover the point.

Points in the table: within ``TABLE_BAND_MM`` of the arc on the sensor's side (the sphere and its near
neighbourhood); ``on_arc`` = inside the segmentation's band, ``kept`` = on the arc and within the border angle.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np

from ..preprocess.profile_arc import ARC_MAX_ANGLE_DEG, ArcFitError, segment_sphere_arc
from ..scan.profiles import ProfileRecord

__all__ = ["MAX_GAP_MM", "PROFILE_FEATURES", "TABLE_BAND_MM", "ProfileTable", "build_profile_table",
           "profile_features"]

PROFILE_FEATURES = ["u", "w", "inc_plane", "arc_curvature"]
TABLE_BAND_MM = 0.3
MAX_GAP_MM = 0.5


def profile_features(xz: np.ndarray, angle_deg: np.ndarray, arc_radius: float) -> np.ndarray:
    """(M, 4) float32 ``PROFILE_FEATURES`` of points ``xz`` (M, 2) mm with in-plane normal angles (deg) on an arc
    of radius ``arc_radius`` (mm)."""
    xz = np.asarray(xz, dtype=np.float64)
    return np.column_stack([xz[:, 0], xz[:, 1], np.asarray(angle_deg, dtype=np.float64),
                            np.full(len(xz), 1.0 / max(float(arc_radius), 1e-9))]).astype(np.float32)


@dataclass
class ProfileTable:
    """Arc points of P profiles (M points in all); lengths mm, angles deg.

    Attributes:
        names, positions, sides: per profile (P,).
        radius: certified sphere radius, mm; arc_radius (P,), arc_center (P, 2), arc_rms (P,) per profile.
        failures: profiles with no arc: name → reason.
        profile: (M,) profile index of each point; index: (M,) the point's row in its file.
        xz: (M, 2) points; normals: (M, 2) outward arc normals; angle: (M,) in-plane normal angle.
        deviation: (M,) nominal − measured along the normal; errors: (M, 3) per axis.
        X: (M, F) float32 features; feature_names: their names.
        on_arc, kept: (M,) masks (module doc); label: (M,) int8 file labels (−1 where none).
        systematic, spread: (M,) repeat mean / std of the deviation (NaN where fewer than 1 / 2 repeats);
        n_repeats: (M,) repeats covering the point.
        toward: (P,) +1 where the sensor sits at larger z than the sphere (it looks down −z), −1 otherwise.
        label1_count: (P,) label-1 points in each profile's whole file (−1 without labels), to score segmentations.
    """

    names: list[str]
    positions: list[str]
    sides: np.ndarray
    radius: float
    arc_radius: np.ndarray
    arc_center: np.ndarray
    arc_rms: np.ndarray
    profile: np.ndarray
    index: np.ndarray
    xz: np.ndarray
    normals: np.ndarray
    angle: np.ndarray
    deviation: np.ndarray
    errors: np.ndarray
    X: np.ndarray
    on_arc: np.ndarray
    kept: np.ndarray
    label: np.ndarray
    systematic: np.ndarray
    spread: np.ndarray
    n_repeats: np.ndarray
    label1_count: np.ndarray | None = None
    toward: np.ndarray | None = None
    feature_names: list[str] = field(default_factory=lambda: list(PROFILE_FEATURES))
    failures: dict[str, str] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.deviation)

    def position_ids(self) -> np.ndarray:
        """(M,) int id of each point's position (repeats share it)."""
        _, inv = np.unique(np.asarray(self.positions, dtype=object).astype(str), return_inverse=True)
        return inv[self.profile]

    def select(self, profiles: np.ndarray) -> np.ndarray:
        """(M,) mask of the points of the given profile indices."""
        return np.isin(self.profile, np.asarray(profiles, dtype=np.int64))


def _interp_gapped(x_src: np.ndarray, v_src: np.ndarray, x_at: np.ndarray) -> np.ndarray:
    """Linear interpolation of v(x) at ``x_at``; NaN outside the range or across a gap wider than MAX_GAP_MM."""
    o = np.argsort(x_src)
    xs, vs = x_src[o], v_src[o]
    out = np.interp(x_at, xs, vs, left=np.nan, right=np.nan)
    j = np.clip(np.searchsorted(xs, x_at), 1, max(len(xs) - 1, 1))
    if len(xs) >= 2:
        out[(xs[j] - xs[j - 1]) > MAX_GAP_MM] = np.nan
    return out


def build_profile_table(records: list[ProfileRecord], sphere_radius: float, *,
                        max_angle_deg: float = ARC_MAX_ANGLE_DEG, seed: int = 0) -> ProfileTable:
    """The table of ``records`` (module doc). Profiles without an arc are listed in ``failures`` and left out;
    ValueError when none has one."""
    R = float(sphere_radius)
    cols: dict[str, list[np.ndarray]] = defaultdict(list)
    names: list[str] = []
    positions: list[str] = []
    sides: list[int] = []
    radii: list[float] = []
    centres: list[np.ndarray] = []
    rms: list[float] = []
    n_label1: list[int] = []
    toward: list[int] = []
    failures: dict[str, str] = {}
    for rec in records:
        try:
            seg = segment_sphere_arc(rec.xz, R, max_angle_deg=max_angle_deg, seed=seed)
        except ArcFitError as e:
            failures[rec.name] = str(e)
            continue
        sel = (np.abs(seg.residual) < TABLE_BAND_MM) & (np.abs(seg.angle_deg) < 90.0)
        k = len(names)
        names.append(rec.name)
        positions.append(rec.position)
        sides.append(rec.side)
        radii.append(seg.radius)
        centres.append(seg.center)
        rms.append(seg.rms)
        toward.append(seg.toward)
        n_label1.append(int(np.sum(rec.label == 1)) if rec.label is not None else -1)
        idx = np.flatnonzero(sel)
        dev = -seg.residual[idx]
        n2 = seg.normals[idx]
        cols["profile"].append(np.full(len(idx), k, dtype=np.int64))
        cols["index"].append(idx)
        cols["xz"].append(rec.xz[idx])
        cols["normals"].append(n2)
        cols["angle"].append(seg.angle_deg[idx])
        cols["deviation"].append(dev)
        cols["errors"].append(np.column_stack([dev * n2[:, 0], np.zeros(len(idx)), dev * n2[:, 1]]))
        cols["X"].append(profile_features(rec.xz[idx], seg.angle_deg[idx], seg.radius))
        cols["on_arc"].append(seg.on_arc[idx])
        cols["kept"].append(seg.kept[idx])
        cols["label"].append(rec.label[idx] if rec.label is not None else np.full(len(idx), -1, np.int8))
    if not names:
        raise ValueError(f"no profile holds an arc of a {R:g} mm sphere "
                         f"({len(failures)} failures, e.g. {next(iter(failures.items()), ('', ''))})")
    cat = {k: np.concatenate(v) for k, v in cols.items()}
    sysm, spread, nrep = _repeat_stats(cat, positions)
    return ProfileTable(names=names, positions=positions, sides=np.asarray(sides, dtype=np.int8), radius=R,
                        arc_radius=np.asarray(radii), arc_center=np.asarray(centres), arc_rms=np.asarray(rms),
                        profile=cat["profile"], index=cat["index"], xz=cat["xz"], normals=cat["normals"],
                        angle=cat["angle"], deviation=cat["deviation"], errors=cat["errors"], X=cat["X"],
                        on_arc=cat["on_arc"], kept=cat["kept"], label=cat["label"], systematic=sysm, spread=spread,
                        n_repeats=nrep, label1_count=np.asarray(n_label1, dtype=np.int64),
                        toward=np.asarray(toward, dtype=np.int8), failures=failures)


def _repeat_stats(cat: dict[str, np.ndarray], positions: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean, std (ddof 1) and count over the repeats of each point's position of the on-arc deviation at the
    point's x (one vectorised interpolation per pair of repeats; a position has at most a few)."""
    m = len(cat["deviation"])
    total, total2 = np.zeros(m), np.zeros(m)
    count = np.zeros(m, dtype=np.int64)
    by_pos: dict[str, list[int]] = defaultdict(list)
    for k, p in enumerate(positions):
        by_pos[p].append(k)
    # Rows of one profile are contiguous (the table is built profile by profile).
    bounds = np.searchsorted(cat["profile"], np.arange(len(positions) + 1))
    rows_of = {k: np.arange(bounds[k], bounds[k + 1]) for k in range(len(positions))}
    for reps in by_pos.values():
        for k in reps:
            at = rows_of[k]
            x_at = cat["xz"][at, 0]
            for j in reps:
                src = rows_of[j]
                src = src[cat["on_arc"][src]]
                if len(src) < 2:
                    continue
                v = _interp_gapped(cat["xz"][src, 0], cat["deviation"][src], x_at)
                ok = np.isfinite(v)
                total[at[ok]] += v[ok]
                total2[at[ok]] += v[ok] ** 2
                count[at[ok]] += 1
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, total / np.maximum(count, 1), np.nan)
        var = (total2 - count * mean ** 2) / np.maximum(count - 1, 1)
    spread = np.where(count > 1, np.sqrt(np.clip(var, 0.0, None)), np.nan)
    return mean, spread, count
