"""Find the arc of a sphere of known radius in one laser-line profile and fit it (sensor frame, mm).

A plane cuts a sphere of radius R in a circle of radius r ≤ R, so a profile of a sphere holds a circular arc of
unknown centre and radius r ≤ R, among points of the mount, the table and stray returns. The search is robust and
uses no labels:

1. RANSAC over circles through three profile points (seeded, vectorised): a circle of radius in
   [``min_radius_fraction`` · R, 1.01 · R] with the most points within ``band_mm`` wins (a flat table or a
   straight post does not fit a circle that small);
2. least-squares refits on the points within ``band_mm``, then within max(4 robust σ, ``min_band_mm``) of the
   refitted circle (three rounds), restricted to the half of the circle that faces the sensor; a refitted radius
   above 1.01 R is refused (the RANSAC circle was a local piece of a larger curve);
3. an arc that spans less than ``min_span_deg`` of kept normal angles is refused: a short piece of a larger curve
   (a fillet, a bigger sphere) fits a circle of the sphere's size locally, a sphere's section facing the sensor
   shows 100-130° (real profiles: 102° at least; clipped ones 70°);
4. the sphere points the product keeps (``kept``) are those arc points whose outward normal is within
   ``max_angle_deg`` of the sensor's axis (the z axis, sign toward the sensor): beyond it the surface is seen at
   grazing angles and the labeller of the real data set, like the product's grazing flag, calls it border.

Normals are the fitted arc's outward in-plane normals (n_x, n_z); the sphere's out-of-plane component
(|n_y| = |y0| / R, y0 = ±sqrt(R² − r²)) is in :func:`sphere_offset`. Angles in degrees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ARC_MAX_ANGLE_DEG", "ArcFitError", "ArcSegment", "segment_sphere_arc", "sphere_offset"]

#: The in-plane angle between normal and sensor axis beyond which arc points are border (grazing), degrees.
#: Chosen on the real data set's training list (docs/real-data.md: segmentation IoU against its labels by angle).
ARC_MAX_ANGLE_DEG = 66.0


class ArcFitError(ValueError):
    """No circular arc of the sphere's size in the profile."""


@dataclass
class ArcSegment:
    """A sphere arc found in a profile of N points.

    Attributes:
        center: (2,) arc centre (x, z), mm.
        radius: arc radius r, mm (≤ R up to noise).
        rms: RMS radial residual of the arc points, mm.
        on_arc: (N,) points on the fitted arc (inside the refit band, facing the sensor).
        kept: (N,) arc points within ``max_angle_deg`` of the sensor axis: the sphere points the product keeps.
        normals: (N, 2) outward unit normal of the arc at each point's projection (x, z).
        angle_deg: (N,) signed in-plane angle of that normal from the sensor axis, degrees.
        residual: (N,) radial residual |p − c| − r, mm (outward positive).
        toward: +1 if the sensor looks down the −z axis (it sits at larger z), −1 otherwise.
    """

    center: np.ndarray
    radius: float
    rms: float
    on_arc: np.ndarray
    kept: np.ndarray
    normals: np.ndarray
    angle_deg: np.ndarray
    residual: np.ndarray
    toward: int


def sphere_offset(radius: float, arc_radius: float, side: int) -> float:
    """The sphere centre's y (mm) for a laser plane cutting a sphere of ``radius`` in an arc of ``arc_radius``:
    ``side`` · sqrt(R² − r²) (0 when r ≥ R)."""
    return float(side) * float(np.sqrt(max(radius * radius - arc_radius * arc_radius, 0.0)))


def _circles_through(p1: np.ndarray, p2: np.ndarray, p3: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centres (T, 2) and radii (T,) of the circles through point triples (NaN where collinear)."""
    ax, az = p1[:, 0], p1[:, 1]
    bx, bz = p2[:, 0], p2[:, 1]
    cx, cz = p3[:, 0], p3[:, 1]
    d = 2.0 * (ax * (bz - cz) + bx * (cz - az) + cx * (az - bz))
    with np.errstate(divide="ignore", invalid="ignore"):
        a2, b2, c2 = ax * ax + az * az, bx * bx + bz * bz, cx * cx + cz * cz
        ux = (a2 * (bz - cz) + b2 * (cz - az) + c2 * (az - bz)) / d
        uz = (a2 * (cx - bx) + b2 * (ax - cx) + c2 * (bx - ax)) / d
    centres = np.stack([ux, uz], axis=1)
    return centres, np.hypot(ax - ux, az - uz)


def _lsq_circle(xz: np.ndarray) -> tuple[np.ndarray, float]:
    """Algebraic (Kåsa) fit then three Gauss-Newton steps of the geometric fit."""
    x, z = xz[:, 0], xz[:, 1]
    A = np.column_stack([2 * x, 2 * z, np.ones_like(x)])
    s = np.linalg.lstsq(A, x * x + z * z, rcond=None)[0]
    c = s[:2].copy()
    r = float(np.sqrt(max(s[2] + c @ c, 1e-12)))
    for _ in range(3):
        d = xz - c
        rho = np.hypot(d[:, 0], d[:, 1])
        rho = np.where(rho > 1e-12, rho, 1e-12)
        J = np.column_stack([-d[:, 0] / rho, -d[:, 1] / rho, -np.ones_like(rho)])
        step = np.linalg.lstsq(J, -(rho - r), rcond=None)[0]
        c = c + step[:2]
        r = float(r + step[2])
    return c, r


def segment_sphere_arc(
    xz: np.ndarray, sphere_radius: float, *, max_angle_deg: float = ARC_MAX_ANGLE_DEG, band_mm: float = 0.3,
    min_band_mm: float = 0.06, min_radius_fraction: float = 0.25, min_points: int = 12, min_span_deg: float = 45.0,
    trials: int = 600, seed: int = 0,
) -> ArcSegment:
    """Find and fit the arc of a sphere of ``sphere_radius`` (mm) in one profile ``xz`` (N, 2) mm (module doc).

    Raises ArcFitError when no circle of the sphere's size holds ``min_points`` points."""
    p = np.asarray(xz, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"xz must be (N, 2), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError("xz holds non-finite points: drop the no-return points first")
    n = len(p)
    if n < max(min_points, 3):
        raise ArcFitError(f"{n} points: too few for an arc of {min_points}")
    R = float(sphere_radius)
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, n, size=(trials, 3))
    ok = (idx[:, 0] != idx[:, 1]) & (idx[:, 1] != idx[:, 2]) & (idx[:, 0] != idx[:, 2])
    idx = idx[ok]
    cen, rad = _circles_through(p[idx[:, 0]], p[idx[:, 1]], p[idx[:, 2]])
    good = np.isfinite(rad) & (rad >= min_radius_fraction * R) & (rad <= 1.01 * R)
    if not np.any(good):
        raise ArcFitError(f"no circle of radius {min_radius_fraction * R:.1f}-{1.01 * R:.1f} mm through the profile")
    cen, rad = cen[good], rad[good]
    # Inlier counts of every candidate over every point: (T, N), a few hundred × a few thousand.
    dist = np.abs(np.hypot(p[None, :, 0] - cen[:, None, 0], p[None, :, 1] - cen[:, None, 1]) - rad[:, None])
    counts = (dist < band_mm).sum(axis=1)
    best = int(np.argmax(counts))
    if counts[best] < min_points:
        raise ArcFitError(f"the best circle holds {int(counts[best])} points (< {min_points})")
    inl = dist[best] < band_mm
    c, r = _lsq_circle(p[inl])
    toward = 1
    for _ in range(3):
        d = p - c
        rho = np.hypot(d[:, 0], d[:, 1])
        res = rho - r
        # The sensor sees the near half of the sphere: the side where the arc's points lie.
        toward = 1 if np.median(d[inl, 1]) >= 0 else -1
        s = 1.4826 * np.median(np.abs(res[inl] - np.median(res[inl])))
        inl = (np.abs(res) < min(max(4.0 * s, min_band_mm), band_mm)) & (toward * d[:, 1] > 0)
        if inl.sum() < min_points:
            raise ArcFitError(f"only {int(inl.sum())} points stay on the refitted arc (< {min_points})")
        c, r = _lsq_circle(p[inl])
    if r > 1.01 * R:
        raise ArcFitError(f"the refitted arc has radius {r:.2f} mm > the sphere's {R:g} mm: not a section of it")
    d = p - c
    rho = np.hypot(d[:, 0], d[:, 1])
    res = rho - r
    nrm = d / np.where(rho > 1e-12, rho, 1e-12)[:, None]
    angle = np.degrees(np.arctan2(nrm[:, 0], toward * nrm[:, 1]))
    s = 1.4826 * np.median(np.abs(res[inl] - np.median(res[inl])))
    on_arc = (np.abs(res) < min(max(4.0 * s, min_band_mm), band_mm)) & (np.abs(angle) < 90.0)
    kept = on_arc & (np.abs(angle) <= max_angle_deg)
    if kept.sum() < min_points:
        raise ArcFitError(f"only {int(kept.sum())} arc points within {max_angle_deg:g}° of the sensor axis")
    span = float(np.ptp(angle[kept]))
    if span < min_span_deg:
        raise ArcFitError(f"the arc spans {span:.0f}° (< {min_span_deg:g}°): a piece of another curve, not the "
                          "sphere's section facing the sensor")
    return ArcSegment(center=c, radius=float(r), rms=float(np.sqrt(np.mean(res[on_arc] ** 2))), on_arc=on_arc,
                      kept=kept, normals=nrm, angle_deg=angle, residual=res, toward=toward)
