"""Artifacts from their specifications: ``artifact_from_dict`` (inverse of every kind's ``to_dict``: sphere,
cylinder, plane, mesh, generated part) and ``parse_artifact`` (the command line's ``sphere:radius=40,...``).

This module sits above ``artifacts`` (the analytic shapes), ``mesh`` (``MeshArtifact``) and ``generated_parts``
so that none of those three needs another's reader: the one place that knows every kind. Lengths in mm.
"""

from __future__ import annotations

import numpy as np

from .artifacts import Artifact, ArtifactSpecError, Cylinder, Plane, Sphere
from .generated_parts import make_part
from .mesh import MeshArtifact

__all__ = ["artifact_from_dict", "mesh_from_dict", "parse_artifact"]


def artifact_from_dict(d: dict) -> Artifact:
    """Inverse of ``Artifact.to_dict``."""
    kind = d.get("kind")
    if kind == "sphere":
        return Sphere(float(d["radius"]), tuple(d.get("center", (0, 0, 0))))
    if kind == "cylinder":
        return Cylinder(float(d["radius"]), tuple(d.get("center", (0, 0, 0))), tuple(d.get("axis", (0, 1, 0))))
    if kind == "plane":
        return Plane(tuple(d.get("point", (0, 0, 0))), tuple(d.get("normal", (0, 0, 1))))
    if kind == "mesh":  # a triangle mesh (its queries need open3d)
        return mesh_from_dict(d)
    raise ArtifactSpecError(f"unknown artifact kind {kind!r} (known: sphere, cylinder, plane, mesh)")


def parse_artifact(spec: str) -> tuple[Artifact, bool]:
    """Parse ``sphere:radius=40[,center=x;y;z|center=fit]``, ``cylinder:radius=20[,center=..][,axis=x;y;z]`` or
    ``plane[:point=..,normal=..]`` (mm). Returns the artifact and whether its centre is to be fitted
    (``center=fit``: centre fitted with the nominal radius fixed)."""
    if not isinstance(spec, str) or not spec.strip():
        raise ArtifactSpecError("empty artifact specification")
    kind, _, rest = spec.strip().partition(":")
    kind = kind.strip().lower()
    opts: dict[str, str] = {}
    for part in filter(None, (p.strip() for p in rest.split(","))):
        key, eq, val = part.partition("=")
        if not eq:
            raise ArtifactSpecError(f"artifact option {part!r} in {spec!r} is not key=value")
        opts[key.strip().lower()] = val.strip()

    def vec(name: str, default: tuple[float, float, float]) -> tuple[float, float, float]:
        if name not in opts:
            return default
        try:
            v = tuple(float(x) for x in opts[name].split(";"))
        except ValueError as e:
            raise ArtifactSpecError(f"{name}={opts[name]!r} in {spec!r} is not three numbers separated by ';'") from e
        if len(v) != 3:
            raise ArtifactSpecError(f"{name} in {spec!r} needs three numbers separated by ';'")
        return v

    fit = opts.get("center", "").lower() == "fit"
    if fit:
        opts.pop("center")
    allowed = {"sphere": {"radius", "center"}, "cylinder": {"radius", "center", "axis"}, "plane": {"point", "normal"}}
    if kind not in allowed:
        raise ArtifactSpecError(f"unknown artifact kind {kind!r} in {spec!r} (known: sphere, cylinder, plane)")
    unknown = set(opts) - allowed[kind]
    if unknown:
        raise ArtifactSpecError(f"unknown option(s) {sorted(unknown)} for {kind} in {spec!r}")
    if kind == "plane":
        return Plane(vec("point", (0.0, 0.0, 0.0)), vec("normal", (0.0, 0.0, 1.0))), False
    if "radius" not in opts:
        raise ArtifactSpecError(f"{kind} in {spec!r} needs radius=<mm>")
    try:
        radius = float(opts["radius"])
    except ValueError as e:
        raise ArtifactSpecError(f"radius={opts['radius']!r} in {spec!r} is not a number") from e
    if kind == "sphere":
        return Sphere(radius, vec("center", (0.0, 0.0, 0.0))), fit
    return Cylinder(radius, vec("center", (0.0, 0.0, 0.0)), vec("axis", (0.0, 1.0, 0.0))), fit


def mesh_from_dict(d: dict) -> MeshArtifact:
    """Inverse of ``MeshArtifact.to_dict``."""
    crease = float(d.get("crease_deg", 30.0))
    t = np.asarray(d.get("transform", np.eye(4)), dtype=np.float64)
    src = d.get("source")
    if src is not None and "part" in src:
        base = make_part(**src)
        base = MeshArtifact(base.vertices, base.triangles, name=base.name, source=base.source, crease_deg=crease)
    elif src is not None and "path" in src:
        base = MeshArtifact.from_file(src["path"], crease_deg=crease)
    elif "vertices" in d and "triangles" in d:
        base = MeshArtifact(np.asarray(d["vertices"]), np.asarray(d["triangles"]), name=str(d.get("name", "mesh")),
                            crease_deg=crease)
    else:
        raise ArtifactSpecError("a mesh artifact needs a source (part or path) or vertices and triangles")
    return base if np.allclose(t, np.eye(4)) else base.transformed(t)
