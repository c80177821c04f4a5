"""Least-squares fits of spheres, circles and cylinders to points (mm), with vectorised geometric residuals.

Each fit starts from an algebraic (linear) solution and refines the geometric distance residuals with
``scipy.optimize.least_squares`` and an analytic Jacobian. Too few points, non-finite data or a degenerate
configuration raise :class:`FitError`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

__all__ = [
    "FitError",
    "SphereFit",
    "fit_circle_2d",
    "fit_cylinder_center",
    "fit_sphere",
    "fit_sphere_center",
]


class FitError(ValueError):
    """A fit that cannot be made or that does not describe the data (too few points, degenerate, far off)."""


@dataclass(frozen=True)
class SphereFit:
    """A fitted sphere or circle: centre and radius (mm), RMS of the residuals (mm)."""

    center: np.ndarray
    radius: float
    rms: float


def _pts(points: np.ndarray, dim: int, min_n: int) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != dim:
        raise FitError(f"points must have shape (N, {dim}), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise FitError("points contain NaN or inf")
    if len(p) < min_n:
        raise FitError(f"need at least {min_n} points to fit, got {len(p)}")
    return p


def _algebraic(p: np.ndarray) -> tuple[np.ndarray, float]:
    """Linear fit of |p|² = 2 c·p + (r² − |c|²) (works in any dimension), on data centred for conditioning."""
    m = p.mean(axis=0)
    q = p - m
    a = np.hstack([2 * q, np.ones((len(q), 1))])
    b = np.einsum("ij,ij->i", q, q)
    sol, _, rank, _ = np.linalg.lstsq(a, b, rcond=None)
    c = sol[:-1]
    r2 = sol[-1] + c @ c
    if rank < a.shape[1] or not np.all(np.isfinite(sol)) or r2 <= 0:
        raise FitError("degenerate point set: no sphere/circle through it")
    return c + m, float(np.sqrt(r2))


def _refine(p: np.ndarray, c0: np.ndarray, r0: float | None, radius: float | None, loss: str = "linear",
            f_scale: float = 1.0) -> tuple[np.ndarray, float, float]:
    """Geometric fit: minimise Σ (|p − c| − r)²; r fixed to ``radius`` when given."""
    fixed = radius is not None
    d = p.shape[1]

    def split(x: np.ndarray) -> tuple[np.ndarray, float]:
        return (x, float(radius)) if radius is not None else (x[:d], float(x[d]))

    def res(x: np.ndarray) -> np.ndarray:
        c, r = split(x)
        return np.linalg.norm(p - c, axis=1) - r

    def jac(x: np.ndarray) -> np.ndarray:
        c, _ = split(x)
        diff = p - c
        n = np.linalg.norm(diff, axis=1, keepdims=True)
        j = -diff / np.where(n > 0, n, 1)
        return j if fixed else np.hstack([j, -np.ones((len(p), 1))])

    if fixed:
        x0 = c0
    elif r0 is None:
        raise ValueError("a free-radius fit needs a starting radius r0")
    else:
        x0 = np.append(c0, r0)
    sol = least_squares(res, x0, jac=jac, method="lm" if loss == "linear" else "trf", loss=loss, f_scale=f_scale)
    c, r = split(sol.x)
    rr = res(sol.x)
    return c, r, float(np.sqrt(np.mean(rr * rr)))


def fit_sphere(points: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Free-radius sphere fit to (N, 3) points (mm): (center (3,), radius, rms of the radial residuals)."""
    p = _pts(points, 3, 4)
    c0, r0 = _algebraic(p)
    return _refine(p, c0, r0, None)


def fit_sphere_center(points: np.ndarray, radius: float, init: np.ndarray | None = None, *,
                      loss: str = "linear", f_scale: float = 1.0) -> np.ndarray:
    """Centre (3,) of a sphere of known ``radius`` (mm) best fitting (N, 3) points. ``loss`` (scipy names, e.g.
    "soft_l1") makes it robust to clutter. Starts from ``init`` or from the free algebraic fit."""
    if not (np.isfinite(radius) and radius > 0):
        raise FitError(f"radius must be positive, got {radius}")
    p = _pts(points, 3, 3)
    if init is None:
        try:
            init, _ = _algebraic(p)
        except FitError:
            init = p.mean(axis=0)
    c, _, _ = _refine(p, np.asarray(init, dtype=float), None, float(radius), loss=loss, f_scale=f_scale)
    return c


def fit_circle_2d(xz: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Free-radius circle fit to (N, 2) points (mm): (center (2,), radius, rms of the radial residuals)."""
    p = _pts(xz, 2, 3)
    c0, r0 = _algebraic(p)
    return _refine(p, c0, r0, None)


def fit_cylinder_center(points: np.ndarray, radius: float, axis: np.ndarray | tuple = (0.0, 1.0, 0.0),
                        init: np.ndarray | None = None) -> np.ndarray:
    """A point on the axis (3,) of a cylinder of known ``radius`` and axis direction best fitting (N, 3) points:
    a fixed-radius circle fit in the plane normal to the axis (the returned point has zero axial coordinate)."""
    a = np.asarray(axis, dtype=float)
    if a.shape != (3,) or np.linalg.norm(a) < 1e-12:
        raise FitError(f"axis must be a non-zero 3-vector, got {axis}")
    a = a / np.linalg.norm(a)
    p = _pts(points, 3, 3)
    # Orthonormal basis (e1, e2) of the plane normal to the axis.
    e1 = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    q = np.stack([p @ e1, p @ e2], axis=1)
    if init is None:
        try:
            c0, _ = _algebraic(q)
        except FitError:
            c0 = q.mean(axis=0)
    else:
        c0 = np.array([np.asarray(init) @ e1, np.asarray(init) @ e2])
    c, _, _ = _refine(q, c0, None, float(radius))
    return c[0] * e1 + c[1] * e2
