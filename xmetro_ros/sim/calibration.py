"""Calibration of the simulator's noise on real laser-line profiles of a 40 mm radius sphere (AT C5 profiler).

Method (the same for measured and simulated profiles):
1. per profile, clean: drop a flat run of clipped points at the bottom of the measuring range (>= 5 points within
   0.1 mm of the profile's lowest z: p4-p6 of the AT C5 set), fit a circle (algebraic start + Gauss-Newton), drop
   points more than ``GROSS_MM`` off it (spurious returns), refit;
2. bin the residuals by the angle between the point's fitted 2-D normal and the sensor axis (toward the sensor);
3. report the RMS of all residuals of each bin over all profiles (um).

Measured: the 15 p*.yml profiles of ``../shared/data/measured/atc5_profiler_sphere_r40`` (sensor frame, x and z,
mm), read with ``xmetro_ros.scan.measured.load_atc5``. Simulated: a sphere of radius 40 mm scanned with the default
settings and effects by ``calibration_scanner()`` (the default model moved to the AT C5's longer stand-off), 15
profiles picked so that their cut radii match the measured fitted radii (on the camera's +Y side of the centre),
each fitted in the head XZ plane (the laser plane).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..scan.artifacts import Sphere
from ..scan.scanner import ScannerModel
from .scanner_sim import simulate_scan

__all__ = [
    "ANGLE_BINS",
    "GROSS_MM",
    "TOLERANCE",
    "ProfileFit",
    "binned_rms",
    "calibration_table",
    "clean_and_fit",
    "fit_circle",
    "load_atc5_profiles",
    "measured_table",
    "simulated_table",
]

ANGLE_BINS: tuple[tuple[float, float], ...] = ((0.0, 60.0), (60.0, 70.0), (70.0, 80.0), (80.0, 90.0))
GROSS_MM = 0.15
SPHERE_RADIUS_MM = 40.0
ATC5_STANDOFF_MM = 230.0
# Relative tolerance of simulated vs measured RMS per bin (the >80 deg bin holds only ~15 measured points).
TOLERANCE: dict[tuple[float, float], float] = {
    (0.0, 60.0): 0.20,
    (60.0, 70.0): 0.25,
    (70.0, 80.0): 0.25,
    (80.0, 90.0): 0.50,
}


def load_atc5_profiles(directory: str | Path) -> list[np.ndarray]:
    """The 15 AT C5 profiles as (N, 2) arrays of sensor-frame (x, z), mm, in p1..p15 order, uncleaned (the
    cleaning is ``clean_and_fit``'s, applied alike to simulated profiles).

    Reads them with ``xmetro_ros.scan.measured.load_atc5`` (FEAT's loader). Raises FileNotFoundError when the directory
    has no p*.yml, ``measured.MeasuredDataError`` when a file is malformed."""
    from ..scan.measured import load_atc5

    directory = Path(directory)
    if not any(directory.glob("p*.yml")):
        raise FileNotFoundError(f"no AT C5 profiles p*.yml in {directory}")
    return [p.raw_xz if p.raw_xz is not None else p.xz for p in load_atc5(directory, clean=False)]


@dataclass
class ProfileFit:
    """A circle fitted to one measured profile and its residual statistics (mm)."""

    center: np.ndarray  # (2,) mm
    radius: float  # mm
    residuals: np.ndarray  # (N,) mm, signed radial (positive = outside)
    angle_deg: np.ndarray  # (N,) angle of the fitted normal from the sensor axis (+z toward the sensor)
    n_used: int


def fit_circle(xz: np.ndarray, iterations: int = 8) -> tuple[np.ndarray, float, np.ndarray]:
    """Least-squares circle through (N, 2) points: algebraic (Kasa) start, then Gauss-Newton on the geometric
    distance. Returns (centre (2,), radius, signed residuals (N,)), mm."""
    xz = np.asarray(xz, float)
    if len(xz) < 3:
        raise ValueError(f"a circle fit needs >= 3 points, got {len(xz)}")
    x, z = xz[:, 0], xz[:, 1]
    sol = np.linalg.lstsq(np.c_[2 * x, 2 * z, np.ones_like(x)], x * x + z * z, rcond=None)[0]
    c = sol[:2]
    r = float(np.sqrt(sol[2] + c @ c))
    for _ in range(iterations):
        dv = xz - c
        rho = np.linalg.norm(dv, axis=1)
        jac = np.c_[-dv / rho[:, None], -np.ones(len(xz))]
        step = np.linalg.lstsq(jac, -(rho - r), rcond=None)[0]
        c, r = c + step[:2], r + float(step[2])
        if np.abs(step).max() < 1e-10:
            break
    return c, r, np.linalg.norm(xz - c, axis=1) - r


def clean_and_fit(xz: np.ndarray, gross_mm: float = GROSS_MM) -> ProfileFit:
    """Clip removal, circle fit, gross-error removal, refit (see module docstring)."""
    xz = np.asarray(xz, float)
    xz = xz[np.all(np.isfinite(xz), axis=1)]
    low = xz[:, 1] < xz[:, 1].min() + 0.1
    if low.sum() >= 5:
        xz = xz[~low]
    c, r, res = fit_circle(xz)
    xz = xz[np.abs(res) < gross_mm]
    c, r, res = fit_circle(xz)
    nrm = (xz - c) / np.linalg.norm(xz - c, axis=1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip(nrm[:, 1], -1.0, 1.0)))
    return ProfileFit(c, r, res, ang, len(xz))


def binned_rms(fits: list[ProfileFit], bins=ANGLE_BINS) -> dict[tuple[float, float], tuple[float, int]]:
    """RMS (um) and point count of all residuals per angle bin."""
    res = np.concatenate([f.residuals for f in fits])
    ang = np.concatenate([f.angle_deg for f in fits])
    out = {}
    for lo, hi in bins:
        m = (ang >= lo) & (ang < hi)
        out[(lo, hi)] = (float(np.sqrt(np.mean(res[m] ** 2)) * 1e3) if m.any() else float("nan"), int(m.sum()))
    return out


def measured_table(directory: str | Path) -> tuple[dict, list[ProfileFit]]:
    """Binned RMS of the real AT C5 profiles, and their fits."""
    fits = [clean_and_fit(p) for p in load_atc5_profiles(directory)]
    return binned_rms(fits), fits


def calibration_scanner(scanner: ScannerModel | None = None) -> ScannerModel:
    """The scanner model with the AT C5 set-up's geometry: same effects, settings and triangulation angle, but a
    stand-off of ``ATC5_STANDOFF_MM`` (depth of field scaled with it). The real profiles reach ~80 deg normal
    angles on a 40 mm sphere, which a camera at 90 mm cannot see (its tangent limit is ~68 deg), so the sensor
    stood ~2.5 times farther; every stand-off-dependent law is written in units of the depth of field, so the
    scaled model keeps the default's relative behaviour."""
    base = scanner if scanner is not None else ScannerModel.load()
    k = ATC5_STANDOFF_MM / base.standoff_mm
    return dataclasses.replace(
        base,
        standoff_mm=ATC5_STANDOFF_MM,
        camera_mm=(base.camera_mm[0] * k, base.camera_mm[1] * k, base.camera_mm[2] * k),
        depth_of_field_mm=(base.depth_of_field_mm[0] * k, base.depth_of_field_mm[1] * k),
    )


def simulated_table(
    radii_mm: list[float],
    *,
    scanner: ScannerModel | None = None,
    effects: dict[str, Any] | None = None,
    seed: int = 0,
) -> tuple[dict, list[ProfileFit]]:
    """Binned RMS of simulated profiles of a 40 mm radius sphere whose cut radii match ``radii_mm``.

    The scanner is ``calibration_scanner(scanner)``; the sphere's centre sits at its reference stand-off; default
    settings; profiles are the scan rows nearest to the wanted cut."""
    scanner = calibration_scanner(scanner)
    sphere = Sphere(SPHERE_RADIUS_MM, (0.0, 0.0, 0.0))
    scan = simulate_scan(sphere, scanner.default_settings, scanner=scanner, effects=effects, seed=seed)
    ph = scan.pose.to_head(scan.points.reshape(-1, 3)).reshape(scan.points.shape)
    h = scan.shape[0]
    y_rows = scan.pose.to_world(np.c_[np.zeros(h), np.arange(h) / scan.settings.direction_density, np.zeros(h)])[:, 1]
    fits = []
    for _k, r in enumerate(radii_mm):
        y = np.sqrt(max(SPHERE_RADIUS_MM**2 - min(r, SPHERE_RADIUS_MM) ** 2, 0.0))
        row = int(np.argmin(np.abs(y_rows - y)))
        pts = ph[row]
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        if len(pts) < 10:
            continue
        fits.append(clean_and_fit(pts[:, [0, 2]]))
    return binned_rms(fits), fits


def calibration_table(
    directory: str | Path, *, scanner: ScannerModel | None = None, effects: dict[str, Any] | None = None, seed: int = 0
) -> list[dict[str, Any]]:
    """Rows {bin, measured_um, measured_n, simulated_um, simulated_n, ratio, tolerance} for docs and tests."""
    meas, fits = measured_table(directory)
    sim, _ = simulated_table([f.radius for f in fits], scanner=scanner, effects=effects, seed=seed)
    rows = []
    for b in ANGLE_BINS:
        m, mn = meas[b]
        s, sn = sim[b]
        rows.append(
            {
                "bin_deg": b,
                "measured_um": m,
                "measured_n": mn,
                "simulated_um": s,
                "simulated_n": sn,
                "ratio": s / m if m else float("nan"),
                "tolerance": TOLERANCE[b],
            }
        )
    return rows
