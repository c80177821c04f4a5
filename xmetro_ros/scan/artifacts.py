"""Calibrated artifacts (nominal shapes): sphere, cylinder, plane. Lengths in mm, in the scan frame.

Each artifact gives the first ray hit (for the virtual scanner), the outward surface normal, and the projection of
measured points onto its nominal surface — the study's eq. 8-15: radial for a sphere, axial for a cylinder
(the error along the axis is 0), orthogonal for a plane. ``errors(points) = nominal - measured`` per axis.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import unit

__all__ = ["Artifact", "ArtifactSpecError", "Cylinder", "Plane", "Sphere"]


class ArtifactSpecError(ValueError):
    """An artifact specification that does not parse or names an unknown shape."""


class Artifact:
    """Base class: subclasses define ``kind``, ``intersect``, ``normals``, ``project`` and ``to_dict``."""

    kind = "artifact"

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError

    def normals(self, points: np.ndarray) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError

    def project(self, points: np.ndarray) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError

    def errors(self, points: np.ndarray) -> np.ndarray:
        """Per-axis error nominal − measured (mm), shape (N, 3): the study's X_err, Y_err, Z_err."""
        p = _points(points)
        return self.project(p) - p

    def normal_error(self, points: np.ndarray) -> np.ndarray:
        """Signed error along the outward normal (mm; positive = measured inside the surface)."""
        p = _points(points)
        return np.einsum("ij,ij->i", self.errors(p), self.normals(self.project(p)))

    def to_dict(self) -> dict:  # pragma: no cover - interface
        raise NotImplementedError


def _points(points: np.ndarray) -> np.ndarray:
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {p.shape}")
    return p


@dataclass(frozen=True)
class Sphere(Artifact):
    """A sphere of ``radius`` (mm) centred at ``center`` (scan frame, mm)."""

    radius: float
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    kind = "sphere"

    def __post_init__(self) -> None:
        if not (np.isfinite(self.radius) and self.radius > 0):
            raise ArtifactSpecError(f"sphere radius must be positive, got {self.radius}")

    @property
    def c(self) -> np.ndarray:
        return np.asarray(self.center, dtype=float)

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Distance along unit ``dirs`` from ``origins`` to the first hit (NaN where the ray misses)."""
        oc = origins - self.c
        b = np.einsum("ij,ij->i", oc, dirs)
        cc = np.einsum("ij,ij->i", oc, oc) - self.radius**2
        disc = b * b - cc
        with np.errstate(invalid="ignore"):
            t = -b - np.sqrt(disc)
        t[(disc < 0) | (t <= 0)] = np.nan
        return t

    def normals(self, points: np.ndarray) -> np.ndarray:
        return unit(_points(points) - self.c)

    def project(self, points: np.ndarray) -> np.ndarray:
        p = _points(points)
        d = p - self.c
        r = np.linalg.norm(d, axis=1, keepdims=True)
        if np.any(r == 0):
            raise ValueError("a point lies at the sphere centre: its radial projection is undefined")
        return self.c + d * (self.radius / r)

    def to_dict(self) -> dict:
        return {"kind": "sphere", "radius": float(self.radius), "center": [float(x) for x in self.center]}


@dataclass(frozen=True)
class Cylinder(Artifact):
    """Infinite cylinder; the study's has its axis along the scan direction (Y)."""

    radius: float
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis: tuple[float, float, float] = (0.0, 1.0, 0.0)
    kind = "cylinder"

    def __post_init__(self) -> None:
        if not (np.isfinite(self.radius) and self.radius > 0):
            raise ArtifactSpecError(f"cylinder radius must be positive, got {self.radius}")
        if np.linalg.norm(self.axis) < 1e-9:
            raise ArtifactSpecError("cylinder axis must be non-zero")

    @property
    def a(self) -> np.ndarray:
        a = np.asarray(self.axis, dtype=float)
        return a / np.linalg.norm(a)

    def _radial(self, p: np.ndarray) -> np.ndarray:
        d = p - np.asarray(self.center, dtype=float)
        return d - np.outer(d @ self.a, self.a)

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        a = self.a
        oc = origins - np.asarray(self.center, dtype=float)
        d_perp = dirs - np.outer(dirs @ a, a)
        o_perp = oc - np.outer(oc @ a, a)
        qa = np.einsum("ij,ij->i", d_perp, d_perp)
        qb = np.einsum("ij,ij->i", o_perp, d_perp)
        qc = np.einsum("ij,ij->i", o_perp, o_perp) - self.radius**2
        disc = qb * qb - qa * qc
        with np.errstate(invalid="ignore", divide="ignore"):
            t = (-qb - np.sqrt(disc)) / qa
        t[(disc < 0) | (qa < 1e-12) | ~(t > 0)] = np.nan
        return t

    def normals(self, points: np.ndarray) -> np.ndarray:
        return unit(self._radial(_points(points)))

    def project(self, points: np.ndarray) -> np.ndarray:
        p = _points(points)
        rad = self._radial(p)
        r = np.linalg.norm(rad, axis=1, keepdims=True)
        if np.any(r == 0):
            raise ValueError("a point lies on the cylinder axis: its axial projection is undefined")
        return p - rad + rad * (self.radius / r)

    def to_dict(self) -> dict:
        return {
            "kind": "cylinder",
            "radius": float(self.radius),
            "center": [float(x) for x in self.center],
            "axis": [float(x) for x in self.a],
        }


@dataclass(frozen=True)
class Plane(Artifact):
    """A plane through ``point`` with unit ``normal`` (scan frame, mm)."""

    point: tuple[float, float, float] = (0.0, 0.0, 0.0)
    normal: tuple[float, float, float] = (0.0, 0.0, 1.0)
    kind = "plane"

    @property
    def n(self) -> np.ndarray:
        n = np.asarray(self.normal, dtype=float)
        nn = np.linalg.norm(n)
        if nn < 1e-9:
            raise ArtifactSpecError("plane normal must be non-zero")
        return n / nn

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        denom = dirs @ self.n
        with np.errstate(invalid="ignore", divide="ignore"):
            t = ((np.asarray(self.point) - origins) @ self.n) / denom
        t[~(t > 0) | (np.abs(denom) < 1e-12)] = np.nan
        return t

    def normals(self, points: np.ndarray) -> np.ndarray:
        return np.broadcast_to(self.n, _points(points).shape).copy()

    def project(self, points: np.ndarray) -> np.ndarray:
        p = _points(points)
        return p - np.outer((p - np.asarray(self.point)) @ self.n, self.n)

    def to_dict(self) -> dict:
        return {"kind": "plane", "point": [float(x) for x in self.point], "normal": [float(x) for x in self.n]}
