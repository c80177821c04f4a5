"""Loaders for the real measured data sets in ``../shared/data/measured`` (read in place, never copied).

- NIST TLS spheres (``nist_tls_spheres_r50/SPH*.xyz``): terrestrial laser scans of spheres of nominal radius 50 mm,
  metres, scanner at the origin. Converted to mm and cleaned as the data README describes: keep points within
  ``max_angle_deg`` (60°) of the line of sight (angle between the outward normal of the fitted sphere and the
  direction to the scanner) and within ``max_dist_mm`` (10 mm) of the fitted surface. The fit that drives the
  cleaning is robust (soft-L1 loss, radius fixed to 50 mm) and iterated, since the raw files hold the mount
  and background. L = V = the unit direction from each point to the scanner (a TLS is coaxial).
- AT C5 profiles (``atc5_profiler_sphere_r40``): 15 laser-line profiles of a 40 mm sphere, sensor-frame x, z (mm),
  with the Fanuc flange pose of each (x, y, z mm, W, P, R deg; R = Rz(R) Ry(P) Rx(W)) and the hand-eye matrix
  (sensor → flange). ``MeasuredProfile.to_base()`` = flange pose × hand-eye × (x, 0, z). Cleaning: profiles p4-p6
  hold points clipped at the bottom of the measuring range (z ≈ −28.67 mm, a flat run); when at least
  ``ATC5_CLIP_MIN_RUN`` points lie within ``ATC5_CLIP_BAND_MM`` of a profile's lowest z, those points are dropped.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .fitting import FitError, fit_sphere, fit_sphere_center

__all__ = [
    "ATC5_NOMINAL_RADIUS_MM",
    "NIST_NOMINAL_RADIUS_MM",
    "MeasuredCloud",
    "MeasuredDataError",
    "MeasuredProfile",
    "atc5_sphere_fit",
    "fanuc_wpr_to_matrix",
    "load_atc5",
    "load_nist_set",
    "load_nist_sphere",
]

NIST_NOMINAL_RADIUS_MM = 50.0
ATC5_NOMINAL_RADIUS_MM = 40.0
ATC5_CLIP_BAND_MM = 0.1
ATC5_CLIP_MIN_RUN = 5


class MeasuredDataError(ValueError):
    """A measured-data file that is missing, unreadable or malformed."""


@dataclass
class MeasuredCloud:
    """A cleaned measured sphere scan (mm, scanner frame).

    Attributes:
        name: file stem (e.g. "SPH101").
        points: (N, 3) cleaned points, mm.
        raw_points: (R, 3) all points of the file, mm.
        nominal_radius: mm.
        center: (3,) sphere centre fitted with the nominal radius (robust), mm.
        L, V: (N, 3) unit vectors from each point toward the scanner (origin).
        kept: (R,) boolean mask of the raw points kept by the cleaning.
    """

    name: str
    points: np.ndarray
    raw_points: np.ndarray
    nominal_radius: float
    center: np.ndarray
    L: np.ndarray
    V: np.ndarray
    kept: np.ndarray
    meta: dict = field(default_factory=dict)

    def fit(self) -> tuple[np.ndarray, float, float]:
        """Free-radius sphere fit of the cleaned points: (center, radius, rms), mm."""
        return fit_sphere(self.points)


def _read_xyz(path: Path) -> np.ndarray:
    try:
        data = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except (OSError, ValueError) as e:
        raise MeasuredDataError(f"cannot read {path}: {e}") from e
    if data.ndim != 2 or data.shape[1] < 3 or len(data) == 0:
        raise MeasuredDataError(f"{path}: expected rows of x y z, got shape {data.shape}")
    return data[:, :3]


def load_nist_sphere(path: str | Path, *, max_angle_deg: float = 60.0, max_dist_mm: float = 10.0,
                     iterations: int = 4) -> MeasuredCloud:
    """Load one NIST TLS sphere (metres → mm) and clean it (see module doc)."""
    p = Path(path)
    raw = _read_xyz(p) * 1000.0
    raw = raw[np.all(np.isfinite(raw), axis=1)]
    r_nom = NIST_NOMINAL_RADIUS_MM
    # Start: the densest part of the scan is the sphere; the median point is on or near it. Place the centre
    # one radius behind it along the line of sight, then refine robustly with the radius fixed.
    med = np.median(raw, axis=0)
    center = med + r_nom * med / np.linalg.norm(med)
    keep = np.ones(len(raw), dtype=bool)
    cos_max = np.cos(np.radians(max_angle_deg))
    for i in range(iterations):
        sel = raw[keep] if i else raw[np.linalg.norm(raw - center, axis=1) < 2 * r_nom]
        if len(sel) < 10:
            raise MeasuredDataError(f"{p.name}: too few points near the sphere ({len(sel)}) to clean")
        center = fit_sphere_center(sel, r_nom, init=center, loss="soft_l1", f_scale=1.0)
        d = raw - center
        dist = np.linalg.norm(d, axis=1)
        outward = d / dist[:, None]
        to_scanner = -raw / np.linalg.norm(raw, axis=1, keepdims=True)
        keep = (np.abs(dist - r_nom) < max_dist_mm) & (np.einsum("ij,ij->i", outward, to_scanner) > cos_max)
    pts = raw[keep]
    if len(pts) < 10:
        raise MeasuredDataError(f"{p.name}: only {len(pts)} points left after cleaning")
    lv = -pts / np.linalg.norm(pts, axis=1, keepdims=True)
    return MeasuredCloud(name=p.stem, points=pts, raw_points=raw, nominal_radius=r_nom, center=center, L=lv,
                         V=lv.copy(), kept=keep, meta={"source": p.name, "units": "mm (file: m)"})


def load_nist_set(directory: str | Path, **kw) -> list[MeasuredCloud]:
    """All ``SPH*.xyz`` of a directory, sorted by name."""
    d = Path(directory)
    files = sorted(d.glob("SPH*.xyz"))
    if not files:
        raise MeasuredDataError(f"no SPH*.xyz files in {d}")
    return [load_nist_sphere(f, **kw) for f in files]


# ------------------------------------------------------------------------------------------------------------------
# AT C5 profiles on a Fanuc robot


def fanuc_wpr_to_matrix(x: float, y: float, z: float, w: float, p: float, r: float) -> np.ndarray:
    """4×4 pose from Fanuc x, y, z (mm) and W, P, R (deg), fixed-axis XYZ: rotation = Rz(R) Ry(P) Rx(W)."""
    w, p, r = np.radians([w, p, r])
    cw, sw, cp, sp, cr, sr = np.cos(w), np.sin(w), np.cos(p), np.sin(p), np.cos(r), np.sin(r)
    rx = np.array([[1, 0, 0], [0, cw, -sw], [0, sw, cw]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]])
    t = np.eye(4)
    t[:3, :3] = rz @ ry @ rx
    t[:3, 3] = (x, y, z)
    return t


@dataclass
class MeasuredProfile:
    """One laser-line profile of the AT C5 data set.

    Attributes:
        id: profile id ("p1" ... "p15").
        xz: (N, 2) points in the sensor frame (x along the line, z depth), mm.
        flange_pose: 4×4 robot base → flange (mm).
        hand_eye: 4×4 sensor → flange (mm).
        raw_xz: (R, 2) all points of the file (before removing clipped points), mm.
    """

    id: str
    xz: np.ndarray
    flange_pose: np.ndarray
    hand_eye: np.ndarray
    raw_xz: np.ndarray | None = None

    @property
    def points_sensor(self) -> np.ndarray:
        """(N, 3) points (x, 0, z) in the sensor frame, mm."""
        return np.stack([self.xz[:, 0], np.zeros(len(self.xz)), self.xz[:, 1]], axis=1)

    def to_base(self) -> np.ndarray:
        """(N, 3) points in the robot base frame, mm (flange pose × hand-eye × sensor point)."""
        t = self.flange_pose @ self.hand_eye
        return self.points_sensor @ t[:3, :3].T + t[:3, 3]


_FLOAT = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")


def _read_profile(path: Path) -> np.ndarray:
    try:
        text = path.read_text()
    except OSError as e:
        raise MeasuredDataError(f"cannot read {path}: {e}") from e
    m = re.search(r"scan_line:\s*\[(.*?)\]", text, re.S)
    if not m:
        raise MeasuredDataError(f"{path}: no 'scan_line: [...]' list (OpenCV YAML)")
    vals = np.array([float(v) for v in _FLOAT.findall(m.group(1))])
    if len(vals) == 0 or len(vals) % 3:
        raise MeasuredDataError(f"{path}: scan_line has {len(vals)} numbers, expected a multiple of 3 (x, 0, z)")
    xyz = vals.reshape(-1, 3)
    return xyz[:, [0, 2]]


def _clip_mask(xz: np.ndarray) -> np.ndarray:
    """Points clipped at the bottom of the measuring range: a run of >= ATC5_CLIP_MIN_RUN points within
    ATC5_CLIP_BAND_MM of the lowest z (a real sphere profile has a single lowest point)."""
    z = xz[:, 1]
    near = z < z.min() + ATC5_CLIP_BAND_MM
    return near if int(near.sum()) >= ATC5_CLIP_MIN_RUN else np.zeros(len(z), dtype=bool)


def load_atc5(directory: str | Path, clean: bool = True) -> list[MeasuredProfile]:
    """The 15 profiles p1..p15 with their flange poses (RobPoses.rob) and the hand-eye matrix (calibration.sec);
    ``clean`` drops clipped points (see module doc)."""
    d = Path(directory)
    try:
        poses = json.loads((d / "RobPoses.rob").read_text())["RobPoses"]
        calib = json.loads((d / "calibration.sec").read_text())
        hand_eye = np.asarray(calib["Solution"]["HTM"], dtype=float)
    except (OSError, KeyError, ValueError) as e:
        raise MeasuredDataError(f"{d}: cannot read RobPoses.rob / calibration.sec: {e}") from e
    if hand_eye.shape != (4, 4):
        raise MeasuredDataError(f"{d}/calibration.sec: HTM must be 4×4, got {hand_eye.shape}")
    profiles = []
    for i, pose in enumerate(poses, start=1):
        f = d / f"p{i}.yml"
        if len(pose) != 6:
            raise MeasuredDataError(f"{d}/RobPoses.rob: pose {i} must be [x, y, z, W, P, R], got {pose}")
        raw = _read_profile(f)
        xz = raw[~_clip_mask(raw)] if clean else raw
        profiles.append(MeasuredProfile(f"p{i}", xz, fanuc_wpr_to_matrix(*pose), hand_eye, raw_xz=raw))
    if not profiles:
        raise MeasuredDataError(f"{d}: no robot poses")
    return profiles


def atc5_sphere_fit(profiles: list[MeasuredProfile]) -> tuple[np.ndarray, float, float]:
    """Sphere fit (center, radius, rms; mm) of all profiles taken to the robot base."""
    if not profiles:
        raise FitError("no profiles")
    return fit_sphere(np.vstack([p.to_base() for p in profiles]))
