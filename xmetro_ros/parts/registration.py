"""Register a scan to its part's CAD mesh: point-to-plane ICP on the exact mesh, with its uncertainty.
Millimetres; the pose returned is part (CAD) frame → scan frame.

Each iteration takes the exact closest point q and smooth normal n on the CAD (``MeshArtifact.closest``: open3d's
closest-point query refined in float64, so no sampling of the CAD), keeps the pairs closer than
``max_distance_mm``, and solves the linearised point-to-plane least squares Σ ((R p + t − q)·n)² for a small
rotation and translation (Gauss-Newton), until the update is below 1e-7 mm / rad.

Uncertainty, two ways: (1) the spread of the converged poses over ``restarts`` starts perturbed by
``perturb_mm`` / ``perturb_deg`` around the initial pose (how reproducible the minimum is), (2) the covariance
σ²·(JᵀJ)⁻¹ of the 6 pose parameters at the solution, σ the RMS point-to-plane residual (the curvature of the cost
at its minimum; it assumes independent residuals, so it is optimistic when the residual is a smooth systematic
pattern). Reported as standard deviations (mm, degrees), rotations about the axes of the scan frame through the
centroid of the fitted points.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from ..scan.mesh import MeshArtifact

__all__ = ["Registration", "perturbed", "register_to_cad"]


@dataclass
class Registration:
    """Result of :func:`register_to_cad`.

    Attributes:
        pose: (4, 4) part (CAD) frame → scan frame.
        fitness: share of scan points with a CAD correspondence within ``max_distance_mm``.
        rmse_mm: RMS point-to-plane residual of those correspondences (exact distance to the mesh), mm.
        restart_std_mm, restart_std_deg: s.d. of the converged translation (mm, per axis) and rotation (degrees,
            per axis, small-angle) over the perturbed restarts.
        info_std_mm, info_std_deg: s.d. of translation / rotation from σ²·(JᵀJ)⁻¹ (see the module docstring).
    """

    pose: np.ndarray
    fitness: float
    rmse_mm: float
    restart_std_mm: list[float]
    restart_std_deg: list[float]
    info_std_mm: list[float]
    info_std_deg: list[float]

    def to_dict(self) -> dict[str, Any]:
        return {"pose": self.pose.tolist(), "fitness": self.fitness, "rmse_mm": self.rmse_mm,
                "restart_std_mm": self.restart_std_mm, "restart_std_deg": self.restart_std_deg,
                "info_std_mm": self.info_std_mm, "info_std_deg": self.info_std_deg}


def perturbed(pose: np.ndarray, shift_mm: np.ndarray, rot_deg: np.ndarray) -> np.ndarray:
    """``pose`` (4, 4) moved by a rotation ``rot_deg`` (3,) (x-y-z small angles, about the pose's origin) and a
    translation ``shift_mm`` (3,)."""
    from scipy.spatial.transform import Rotation

    t = np.eye(4)
    t[:3, :3] = Rotation.from_euler("xyz", rot_deg, degrees=True).as_matrix()
    t[:3, 3] = shift_mm
    return t @ np.asarray(pose, dtype=np.float64)


def _rotation(w: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return np.asarray(Rotation.from_rotvec(w).as_matrix())


def _icp(p: np.ndarray, cad: MeshArtifact, pose: np.ndarray, max_distance_mm: float, max_iterations: int
         ) -> tuple[np.ndarray, float, float, np.ndarray]:
    """One point-to-plane ICP run from ``pose`` (part → scan). Returns (pose, fitness, rmse mm, covariance of
    (rotation rad, translation mm) (6, 6))."""
    inv = np.linalg.inv(pose)  # scan → part: fitted
    cov: np.ndarray = np.full((6, 6), np.nan)
    fit, rmse = 0.0, float("nan")
    for _ in range(int(max_iterations)):
        x = p @ inv[:3, :3].T + inv[:3, 3]
        q, tri, bary = cad.closest(x)
        n = cad.normals_on(tri, bary)
        r = np.einsum("ij,ij->i", x - q, n)
        keep = np.linalg.norm(x - q, axis=1) < max_distance_mm
        fit = float(keep.mean())
        if keep.sum() < 6:
            break
        c = x[keep].mean(axis=0)
        jac = np.hstack([np.cross(x[keep] - c, n[keep]), n[keep]])  # d r / d (rotation about c, translation)
        jtj = jac.T @ jac
        step = -np.linalg.solve(jtj, jac.T @ r[keep])
        rmse = float(np.sqrt(np.mean(r[keep] ** 2)))
        cov = rmse**2 * np.linalg.inv(jtj)
        upd = np.eye(4)
        upd[:3, :3] = _rotation(step[:3])
        upd[:3, 3] = c - upd[:3, :3] @ c + step[3:]
        inv = upd @ inv
        if np.linalg.norm(step[:3]) < 1e-7 and np.linalg.norm(step[3:]) < 1e-7:
            break
    return np.linalg.inv(inv), fit, rmse, cov


def register_to_cad(points: np.ndarray, cad: MeshArtifact, init_pose: np.ndarray | None = None, *,
                    max_distance_mm: float = 1.0, restarts: int = 3, perturb_mm: float = 0.2,
                    perturb_deg: float = 0.3, seed: int = 0, max_iterations: int = 30,
                    max_points: int = 20_000) -> Registration:
    """Pose of the part ``cad`` (its own frame) in the scan frame of ``points`` (N, 3) mm, by point-to-plane ICP
    from ``init_pose`` (part → scan; None = identity) and ``restarts`` perturbed starts; the run with the best
    fitness, then the lowest RMSE, wins. At most ``max_points`` scan points (an even subsample) enter the fit."""
    from scipy.spatial.transform import Rotation

    p = np.asarray(points, dtype=np.float64)
    p = p[np.isfinite(p).all(axis=1)]
    p = p[:: max(1, -(-len(p) // max_points))]
    if len(p) < 6:
        raise ValueError(f"registration needs at least 6 points, got {len(p)}")
    init = np.eye(4) if init_pose is None else np.asarray(init_pose, dtype=np.float64)
    rng = np.random.default_rng(seed)
    starts = [init] + [perturbed(init, rng.normal(0, perturb_mm, 3), rng.normal(0, perturb_deg, 3))
                       for _ in range(int(restarts))]
    runs = [_icp(p, cad, s, max_distance_mm, max_iterations) for s in starts]
    best = max(runs, key=lambda r: (round(r[1], 4), -r[2]))
    poses = np.stack([r[0] for r in runs])
    rot = Rotation.from_matrix(poses[:, :3, :3] @ poses[0, :3, :3].T).as_rotvec(degrees=True)
    sd = np.sqrt(np.maximum(np.diag(best[3]), 0.0))
    return Registration(pose=best[0], fitness=best[1], rmse_mm=best[2],
                        restart_std_mm=[float(x) for x in poses[:, :3, 3].std(0)],
                        restart_std_deg=[float(x) for x in rot.std(0)],
                        info_std_mm=[float(x) for x in sd[3:]], info_std_deg=[float(x) for x in np.degrees(sd[:3])])
