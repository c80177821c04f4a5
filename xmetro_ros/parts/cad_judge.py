"""Judge a scan against its part's CAD: the deviation map measured − CAD before and after the model's compensation,
with the per-point uncertainty. Millimetres, scan frame (the CAD placed by its pose part → scan).

For each judged point p (finite prediction e = predicted nominal − measured, per axis: the model's target, i.e.
−d for the published deviation d of ``~/deviations``; and U per axis):

- q, n: closest point on the CAD and the CAD's outward normal there;
- ``before`` = (p − q)·n: the raw deviation (positive = material beyond the CAD surface);
- ``after`` = (p + e − q')·n': the same for the compensated point p + e = p − d, ``~/corrected`` (its own closest
  point q', normal n');
- ``u_normal`` = Σ_k |n_k|·U_k: U carried onto the normal (exact when the error lies along the normal, as the
  study's radial projection makes it; an upper bound otherwise, by the triangle inequality).

The CAD's queries (closest points, normals) need open3d (``[train]`` extra), imported on first use by the mesh.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from ..scan.mesh import MeshArtifact
    from .registration import Registration

__all__ = ["CadDeviation", "cad_deviation", "summary_um"]


@dataclass
class CadDeviation:
    """Deviation map of one scan against the CAD (see the module docstring). Per judged point (N,), mm.

    Attributes:
        index: flat indices of the judged points in the scan (or in the points given).
        points: (N, 3) measured points; cad_points: (N, 3) their closest CAD points; normals: (N, 3) CAD normals.
        before, after: signed normal deviation measured − CAD, raw and compensated.
        u_normal: expanded uncertainty (95 %) of ``after`` along the normal (NaN without a calibration).
        flags: (N,) the judge's flag bits of those points (0 when not given).
        pose: (4, 4) part → scan used; registration: the ICP result when the pose was registered.
    """

    index: np.ndarray
    points: np.ndarray
    cad_points: np.ndarray
    normals: np.ndarray
    before: np.ndarray
    after: np.ndarray
    u_normal: np.ndarray
    flags: np.ndarray
    pose: np.ndarray
    registration: Registration | None = None
    notes: list[str] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        """Mean / p95 |deviation| before and after, mean / p95 U along the normal (µm), point count, pose."""
        out: dict[str, Any] = {"points": len(self.index), "before": summary_um(self.before),
                               "after": summary_um(self.after), "u_normal": summary_um(self.u_normal),
                               "pose": self.pose.tolist()}
        if self.registration is not None:
            out["registration"] = self.registration.to_dict()
        return out


def summary_um(x: np.ndarray) -> dict[str, float]:
    """{"mean_abs", "p95_abs", "mean"} of the finite values of ``x`` (mm) in µm (NaN when none)."""
    a = np.asarray(x, dtype=np.float64)
    a = a[np.isfinite(a)]
    if len(a) == 0:
        return {"mean_abs": float("nan"), "p95_abs": float("nan"), "mean": float("nan")}
    return {"mean_abs": float(np.abs(a).mean() * 1e3), "p95_abs": float(np.percentile(np.abs(a), 95) * 1e3),
            "mean": float(a.mean() * 1e3)}


def cad_deviation(cad: MeshArtifact, points: np.ndarray, predicted: np.ndarray, U: np.ndarray | None = None, *,
                  flags: np.ndarray | None = None, pose: np.ndarray | None = None,
                  register: bool = False, register_kwargs: dict[str, Any] | None = None) -> CadDeviation:
    """Deviation map of ``points`` (N, 3) mm (scan frame; NaN rows skipped) with the model's ``predicted`` errors
    (N, 3) mm (NaN = no prediction: skipped) and ``U`` (N, 3) mm against ``cad`` (its own frame).

    ``pose`` (4, 4) part → scan (None = identity). ``register``: refine it by point-to-plane ICP on the
    compensated points (:func:`xmetro_ros.parts.registration.register_to_cad`; its fit and uncertainty are kept in
    ``registration``) — the product registers what it reports.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    e = np.asarray(predicted, dtype=np.float64).reshape(-1, 3)
    u = np.full_like(e, np.nan) if U is None else np.asarray(U, dtype=np.float64).reshape(-1, 3)
    if len(p) != len(e) or len(u) != len(p):
        raise ValueError(f"points {p.shape}, predicted {e.shape} and U {u.shape} must have the same rows")
    ok = np.isfinite(p).all(axis=1) & np.isfinite(e).all(axis=1)
    idx = np.flatnonzero(ok)
    pose_m = np.eye(4) if pose is None else np.asarray(pose, dtype=np.float64)
    reg = None
    if register:
        from .registration import register_to_cad

        reg = register_to_cad(p[idx] + e[idx], cad, pose_m, **(register_kwargs or {}))
        pose_m = reg.pose
    placed = cad.transformed(pose_m)
    q, tri, bary = placed.closest(p[idx])
    n = placed.normals_on(tri, bary)
    before = np.einsum("ij,ij->i", p[idx] - q, n)
    pc = p[idx] + e[idx]
    qc, tric, baryc = placed.closest(pc)
    after = np.einsum("ij,ij->i", pc - qc, placed.normals_on(tric, baryc))
    un = np.einsum("ij,ij->i", np.abs(n), u[idx])
    fl = np.zeros(len(idx), np.uint16) if flags is None else np.asarray(flags).reshape(-1)[idx]
    return CadDeviation(index=idx, points=p[idx], cad_points=q, normals=n, before=before, after=after,
                        u_normal=un, flags=fl, pose=pose_m, registration=reg)
