"""Targets (the study's eq. 8-15): per-axis error = nominal − measured, mm.

This is the *internal* sign (training targets, model outputs, the simulator's errors, the study's tables). What
the product publishes or shows a user is the deviation d = measured − nominal (VIM 2.16, the sign of every CAD
inspection map): :func:`published_deviation` turns a target into it and :func:`study_target` back — the one place
the sign is written (docs/conventions.md, "Errors").

Radial projection onto a sphere, axial onto a cylinder (no error along the axis), orthogonal onto a plane —
``Artifact.errors``. For an artifact not at its nominal position, ``errors_with_fit`` first fits its position
with the nominal radius fixed (sphere centre; cylinder axis position with the axis direction fixed; plane offset
along its normal) and projects onto the fitted artifact.
"""

from __future__ import annotations

import numpy as np

from .artifacts import Artifact, Cylinder, Plane, Sphere
from .fitting import FitError, fit_circle_2d, fit_cylinder_center, fit_sphere, fit_sphere_center
from .geometry import vec3

__all__ = [
    "MAX_FIT_RMS_FRACTION",
    "FitError",
    "errors_with_fit",
    "fit_artifact_position",
    "fit_circle_2d",
    "fit_cylinder_center",
    "fit_sphere",
    "fit_sphere_center",
    "point_errors",
    "published_deviation",
    "study_target",
]

#: A fixed-radius fit whose residual RMS exceeds this fraction of the nominal radius does not describe the data.
MAX_FIT_RMS_FRACTION = 0.05


def _check(points: np.ndarray, artifact: Artifact) -> np.ndarray:
    if not isinstance(artifact, Artifact):
        raise TypeError(f"artifact must be a Sphere, Cylinder or Plane, got {type(artifact).__name__}")
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {p.shape}")
    if len(p) == 0:
        raise ValueError("no points")
    if not np.all(np.isfinite(p)):
        raise ValueError("points contain NaN or inf")
    return p


def published_deviation(target: np.ndarray) -> np.ndarray:
    """The deviation the product publishes, d = measured − nominal, from the study's target t = nominal − measured
    (any shape, any unit): d = −t. Exact in floating point (a sign flip), so the published float32 values are
    those of the target with the sign bit flipped; a NaN (no prediction) stays the very same NaN."""
    return _flip(target)


def study_target(deviation: np.ndarray) -> np.ndarray:
    """The inverse of :func:`published_deviation`: the study's target t = nominal − measured from a published
    deviation d = measured − nominal (read back from ``~/deviations``, an ``xmetro predict`` bag, ``~/explain``)."""
    return _flip(deviation)


def _flip(values: np.ndarray) -> np.ndarray:
    """−values, NaN left as they are (bits included); the dtype kept."""
    v = np.asarray(values)
    return np.where(np.isnan(v), v, np.negative(v)) if v.dtype.kind in "fc" else np.negative(v)


def point_errors(points: np.ndarray, artifact: Artifact) -> np.ndarray:
    """(N, 3) errors nominal − measured (mm) of finite points against the artifact as given (eq. 13-15)."""
    p = _check(points, artifact)
    return artifact.errors(p)


def fit_artifact_position(points: np.ndarray, artifact: Artifact) -> Artifact:
    """The artifact moved to best fit the points, its size and orientation fixed. FitError when the fit fails or
    its RMS exceeds MAX_FIT_RMS_FRACTION of the radius (the nominal radius is far from the data)."""
    p = _check(points, artifact)
    if isinstance(artifact, Sphere):
        c = fit_sphere_center(p, artifact.radius, init=artifact.c)
        fitted: Artifact = Sphere(artifact.radius, vec3(c))
    elif isinstance(artifact, Cylinder):
        a = artifact.a
        c0 = np.asarray(artifact.center, dtype=float)
        c = fit_cylinder_center(p, artifact.radius, a, init=c0)
        c = c + (c0 @ a) * a  # keep the nominal axial position of the centre (irrelevant to axial errors)
        fitted = Cylinder(artifact.radius, vec3(c), vec3(a))
    elif isinstance(artifact, Plane):
        n = artifact.n
        off = float(np.mean((p - np.asarray(artifact.point, dtype=float)) @ n))
        fitted = Plane(vec3(np.asarray(artifact.point, dtype=float) + off * n), vec3(n))
        return fitted
    else:  # pragma: no cover - the base class is abstract
        raise TypeError(f"cannot fit the position of a {type(artifact).__name__}")
    rms = float(np.sqrt(np.mean(fitted.normal_error(p) ** 2)))
    if not np.isfinite(rms) or rms > MAX_FIT_RMS_FRACTION * artifact.radius:
        raise FitError(
            f"{artifact.kind} of nominal radius {artifact.radius:g} mm does not fit the points: residual RMS "
            f"{rms:.3g} mm after fitting its position (limit {MAX_FIT_RMS_FRACTION * artifact.radius:.3g} mm)"
        )
    return fitted


def errors_with_fit(points: np.ndarray, artifact: Artifact, fit_center: bool) -> tuple[np.ndarray, Artifact]:
    """(errors (N, 3) mm, artifact used): against the artifact as given, or — ``fit_center`` — against the artifact
    with its position fitted (nominal radius fixed; see fit_artifact_position)."""
    used = fit_artifact_position(points, artifact) if fit_center else artifact
    return point_errors(points, used), used
