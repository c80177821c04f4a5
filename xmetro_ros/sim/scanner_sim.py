"""The virtual laser line scanner: casts the whole organized grid of laser rays at once and applies the effects.

Geometry (head frame, see xmetro_ros.scan.geometry): the laser source sits at the head origin; the fan lies in the head
XZ plane, pointing along head -Z; profile i is taken after the head moved ``i / direction_density`` mm along head +Y;
within a profile, ray j passes through head X = ``j / lateral_density`` mm on the reference plane (stand-off
``scanner.standoff_mm``), so the lateral spacing is 1 / lateral_density at the reference distance. The camera sits
``baseline_mm`` along head +Y from the source. A ray returns a point when it hits the artifact, the camera sees
the hit (N·V > 0 and the segment to the camera does not hit the artifact), and no effect drops it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..scan.artifacts import Artifact, ArtifactSpecError, Cylinder, Plane, Sphere
from ..scan.geometry import HeadPose
from ..scan.mesh import MeshArtifact
from ..scan.scan import Scan
from ..scan.scanner import ScannerModel, ScanSettings, SettingsError
from .effect import SimContext
from .effects import EFFECTS, resolve_effects

__all__ = ["DEFAULT_EXTENT_MM", "MARGIN_MM", "ScanGrid", "error_noise_std", "scan_grid", "simulate_scan"]

DEFAULT_EXTENT_MM = 40.0  # scanned length of a cylinder along its axis / side of a plane patch
MARGIN_MM = 1.0  # extra scan length on each side of the artifact


class ScanGrid:
    """Rays of one scan: profile offsets s (H,), line positions u at the reference plane (W,), timing."""

    def __init__(self, pose: HeadPose, s: np.ndarray, u: np.ndarray, period_s: float, scanner: ScannerModel):
        self.pose, self.s, self.u, self.period_s, self.scanner = pose, s, u, period_s, scanner

    @property
    def shape(self) -> tuple[int, int]:
        return (len(self.s), len(self.u))

    def rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Origins and unit directions of all H*W rays in the scan frame, float64, row-major (profile, point)."""
        h, w = self.shape
        r = self.pose.rotation
        o_head = np.zeros((h, 3))
        o_head[:, 1] = self.s
        d_head = np.stack([self.u, np.zeros(w), -np.full(w, self.scanner.standoff_mm)], axis=1)
        d_head /= np.linalg.norm(d_head, axis=1, keepdims=True)
        origins = np.repeat(self.pose.to_world(o_head), w, axis=0)
        dirs = np.tile(d_head @ r.T, (h, 1))
        return origins, dirs


def _bounds_corners(artifact: Artifact, extent_mm: float) -> np.ndarray:
    """Corners (8, 3) of a box holding the part of the artifact that is scanned (scan frame, mm)."""
    if isinstance(artifact, Sphere):
        c, h = artifact.c, np.full(3, artifact.radius)
        axes = np.eye(3) * h
    elif isinstance(artifact, Cylinder):
        c = np.asarray(artifact.center, float)
        a = artifact.a
        e1 = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 0, 1.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(a, e1)
        axes = np.stack([a * extent_mm / 2, e1 * artifact.radius, e2 * artifact.radius])
    elif isinstance(artifact, Plane):
        c, n = np.asarray(artifact.point, float), artifact.n
        t1 = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(n, t1)
        axes = np.stack([t1 * extent_mm / 2, t2 * extent_mm / 2, np.zeros(3)])
    elif isinstance(artifact, MeshArtifact):
        lo, hi = artifact.bounds()
        c, axes = 0.5 * (lo + hi), np.diag(0.5 * (hi - lo))
    else:
        raise ArtifactSpecError(
            f"unknown artifact type {type(artifact).__name__!r} (the simulator scans Sphere, Cylinder, Plane)"
        )
    signs = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)
    return c + signs @ axes


def scan_grid(
    artifact: Artifact,
    settings: ScanSettings,
    scanner: ScannerModel,
    pose: HeadPose | None = None,
    extent_mm: float = DEFAULT_EXTENT_MM,
    window: tuple[float, float, float, float] | None = None,
) -> ScanGrid:
    """Rows and columns that cover the artifact. ``pose`` None → looking down from ``scanner.standoff_mm`` above
    the origin, starting ``MARGIN_MM`` before the artifact; given → the scan starts at ``pose``. ``window``
    (s_lo, s_hi, u_lo, u_hi), mm in the head frame of ``pose`` (s: travel along head +Y, u: line position at the
    reference stand-off) keeps only the rows and columns inside it (the same rays as the full scan, fewer of them)."""
    corners = _bounds_corners(artifact, extent_mm)
    if pose is None:
        h0 = HeadPose.looking_down(scanner.standoff_mm)
        y0 = h0.to_head(corners)[:, 1].min() - MARGIN_MM
        pose = HeadPose.looking_down(scanner.standoff_mm, y_mm=float(y0))
    ch = pose.to_head(corners)
    s_max = ch[:, 1].max() + MARGIN_MM
    if s_max <= 0:
        raise ValueError("the artifact lies behind the scan start: nothing to scan from this pose")
    h = int(np.floor(s_max * settings.direction_density)) + 1
    i0 = 0
    if window is not None:  # same row positions as the full scan, restricted to the window
        i0 = max(0, int(np.ceil(window[0] * settings.direction_density)))
        h = min(h, int(np.floor(window[1] * settings.direction_density)) + 1)
        if h <= i0:
            raise ValueError("the scan window holds no profile")
    s = np.arange(i0, h) / settings.direction_density
    # Column range: corners projected along the rays onto the reference plane, limited by the fan.
    r_ref = scanner.standoff_mm
    u_fan = r_ref * np.tan(np.radians(scanner.fan_angle_deg / 2))
    below = ch[:, 2] < 0
    if not below.any():
        raise ValueError("the artifact is not below the scanner head (head -Z): nothing to scan from this pose")
    if below.all():
        u_c = ch[:, 0] * r_ref / -ch[:, 2]
        lo, hi = max(u_c.min() - MARGIN_MM, -u_fan), min(u_c.max() + MARGIN_MM, u_fan)
    else:
        lo, hi = -u_fan, u_fan
    if window is not None:
        lo, hi = max(lo, window[2]), min(hi, window[3])
    if lo >= hi:
        raise ValueError("the artifact is outside the laser fan")
    lat = settings.lateral_density
    u = np.arange(int(np.ceil(lo * lat)), int(np.floor(hi * lat)) + 1) / lat
    period_s = max(1.0 / scanner.profile_rate_hz, settings.exposure_ms * 1e-3)
    return ScanGrid(pose, s, u, period_s, scanner)


def error_noise_std(artifact: Artifact, points: np.ndarray, cov: np.ndarray, step_mm: float = 1e-4) -> np.ndarray:
    """Std (N, 3) mm of the random part of the per-axis error nominal − measured at noise-free points (N, 3) whose
    Gaussian random displacement has covariance ``cov`` (N, 3, 3) mm².

    The error map e(p) = project(p) − p is linear over the noise's scale (µm against radii of mm), so its random part
    has covariance J·cov·Jᵀ with J the Jacobian of e at the point (central differences, three extra projections of
    the whole cloud); on a sphere J ≈ −n nᵀ: only the normal share of the displacement reaches the error, spread
    over the axes by the normal."""
    p = np.asarray(points, np.float64)
    if len(p) == 0:
        return np.zeros((0, 3))
    jac = np.empty((len(p), 3, 3))
    for k in range(3):
        e = np.zeros(3)
        e[k] = step_mm
        jac[:, :, k] = (artifact.errors(p + e) - artifact.errors(p - e)) / (2 * step_mm)
    var = np.einsum("nij,njk,nik->ni", jac, cov, jac)
    return np.sqrt(np.maximum(var, 0.0))


def _check_inputs(artifact: Any, settings: Any, scanner: ScannerModel) -> None:
    if not isinstance(artifact, (Sphere, Cylinder, Plane, MeshArtifact)):
        raise ArtifactSpecError(
            f"unknown artifact type {type(artifact).__name__!r} (the simulator scans Sphere, Cylinder, Plane, "
            "MeshArtifact)"
        )
    if not isinstance(settings, ScanSettings):
        raise SettingsError(f"settings must be a ScanSettings, got {type(settings).__name__}")
    scanner.validate_settings(settings)


def simulate_scan(
    artifact: Artifact,
    settings: ScanSettings,
    *,
    scanner: ScannerModel | None = None,
    pose: HeadPose | None = None,
    effects: dict[str, Any] | None = None,
    seed: int = 0,
    frame_id: str = "artifact",
    stamp_ns: int = 0,
    extent_mm: float = DEFAULT_EXTENT_MM,
    keep_context: bool = False,
    window: tuple[float, float, float, float] | None = None,
) -> Scan:
    """Simulate one organized scan of ``artifact``.

    Args:
        artifact: Sphere, Cylinder, Plane or MeshArtifact (any part, xmetro_ros.scan.mesh) in the scan frame (mm).
        settings: lateral density (/mm), direction density (/mm), exposure (ms); validated against the scanner.
        scanner: scanner model; None → ``ScannerModel.load()``.
        pose: head pose at scan start; None → looking down from the scanner's stand-off, covering the artifact.
        effects: overrides of the scanner's ``effects:`` config, {name: {"enabled": bool, param: value}}.
        seed: seed of all random parts (same seed → identical arrays).
        frame_id, stamp_ns: header of the scan.
        extent_mm: scanned length of a cylinder along its axis / side of a plane patch, mm (> 0).
        keep_context: put the SimContext (per-effect contributions) in ``scan.meta["_context"]`` (not JSON-safe;
            for figures and tests).
        window: (s_lo, s_hi, u_lo, u_hi) mm in the head frame of the start pose: simulate only those rows and
            columns of the grid (see ``scan_grid``; a region's re-simulation, xmetro_ros.plan.resim). None → all.

    Returns:
        Scan with points (H, W, 3) mm (NaN = no return), fields intensity, line, t (s), u (mm) as float32,
        ``expected_error`` (H, W, 3) = nominal − noise-free measured point (mm), ``noise_std`` (H, W, 3) = std of
        the random part of the measured error per axis (mm, scan frame; Gaussian noise laws of incidence, speckle
        with its correlation, anisotropy; see :func:`error_noise_std`), ``injected_outlier`` (H, W) bool = the
        spurious returns of the ``outliers`` effect (not Gaussian: excluded from ``noise_std``), and ``meta``
        (effects with their parameters, seed, scanner id, artifact, counts).

    Raises:
        ArtifactSpecError: unknown artifact type. SettingsError: bad settings. UnknownEffectError /
        EffectConfigError: bad effect config. ValueError: non-positive extent or artifact out of view.
    """
    scanner = scanner if scanner is not None else ScannerModel.load()
    _check_inputs(artifact, settings, scanner)
    if not (np.isfinite(extent_mm) and extent_mm > 0):
        raise ValueError(f"extent_mm must be a positive number, got {extent_mm!r}")
    fx = resolve_effects(scanner.effects, effects)
    grid = scan_grid(artifact, settings, scanner, pose, extent_mm, window)
    pose = grid.pose
    h, w = grid.shape
    origins, dirs = grid.rays()
    depth = artifact.intersect(origins, dirs)
    idx = np.flatnonzero(np.isfinite(depth))
    o, d, t = origins[idx], dirs[idx], depth[idx]
    p = o + t[:, None] * d
    n = artifact.normals(p)
    # Camera of the profile that lit the point: at scanner.camera_mm (head frame) from that profile's source.
    cam = o + pose.rotation @ np.asarray(scanner.camera_mm, dtype=float)
    to_cam = cam - p
    dist_cam = np.linalg.norm(to_cam, axis=1)
    v = to_cam / dist_cam[:, None]
    seen = np.einsum("ij,ij->i", n, v) > 1e-6
    # Camera occlusion: the segment point → camera must not hit the artifact again.
    t_occ = artifact.intersect(p + 1e-6 * v, v)
    seen &= ~(t_occ < dist_cam)
    idx, o, d, t, p, n, v = idx[seen], o[seen], d[seen], t[seen], p[seen], n[seen], v[seen]
    ph = pose.to_head(p)
    speed = 1.0 / (settings.direction_density * grid.period_s)
    ctx = SimContext(
        artifact=artifact,
        scanner=scanner,
        settings=settings,
        pose=pose,
        grid_shape=(h, w),
        index=idx,
        origin=o,
        d=d,
        depth=t,
        p=p,
        n=n,
        V=v,
        standoff=-ph[:, 2],
        u_ref=grid.u[idx % w],
        speed_mm_s=speed,
        blur_mm=speed * settings.exposure_ms * 1e-3,
    )
    names = list(EFFECTS)
    for effect in fx:
        # One random stream per effect: switching an effect off does not change the others' noise.
        effect.apply(ctx, np.random.default_rng([int(seed), names.index(effect.name)]))
    keep = ctx.keep
    kidx = idx[keep]
    measured_sys = p[keep] + ctx.sys[keep]
    measured = measured_sys + ctx.rand[keep]

    pts = np.full((h * w, 3), np.nan)
    pts[kidx] = measured
    exp_err = np.full((h * w, 3), np.nan)
    exp_err[kidx] = artifact.errors(measured_sys)
    noise_std = np.full((h * w, 3), np.nan)
    noise_std[kidx] = error_noise_std(artifact, measured_sys, ctx.rand_cov[keep])
    injected = np.zeros(h * w, bool)
    injected[np.asarray(ctx.stats.get("outlier_index", []), dtype=np.int64)] = True
    rows = np.repeat(np.arange(h, dtype=np.float32), w)
    line = np.full(h * w, np.nan, np.float32)
    line[kidx] = rows[kidx]
    tt = np.full(h * w, np.nan, np.float32)
    tt[kidx] = (rows[kidx] * grid.period_s).astype(np.float32)
    uu = np.full(h * w, np.nan, np.float32)
    uu[kidx] = pose.to_head(measured)[:, 0].astype(np.float32)
    inten = np.full(h * w, np.nan, np.float32)
    inten[kidx] = np.clip(ctx.intensity[keep], 0.0, 1.0).astype(np.float32)
    meta: dict[str, Any] = {
        "effects": {e.name: dict(e.params) for e in fx},
        "seed": int(seed),
        "scanner": scanner.id,
        "artifact": artifact.to_dict(),
        "settings": {
            "lateral_density": settings.lateral_density,
            "direction_density": settings.direction_density,
            "exposure_ms": settings.exposure_ms,
        },
        "head_speed_mm_s": float(speed),
        "blur_mm": float(ctx.blur_mm),
        "n_points": len(kidx),
        "n_outliers": int(ctx.stats.get("outliers", 0)),
    }
    if keep_context:
        meta["_context"] = ctx
    return Scan(
        points=pts.reshape(h, w, 3),
        settings=settings,
        pose=pose,
        scanner_id=scanner.id,
        fields={
            "intensity": inten.reshape(h, w),
            "line": line.reshape(h, w),
            "t": tt.reshape(h, w),
            "u": uu.reshape(h, w),
        },
        frame_id=frame_id,
        stamp_ns=int(stamp_ns),
        artifact=artifact,
        expected_error=exp_err.reshape(h, w, 3),
        noise_std=noise_std.reshape(h, w, 3),
        injected_outlier=injected.reshape(h, w),
        meta=meta,
    )
