"""Artifacts from their specifications: ``artifact_from_dict`` (inverse of every kind's ``to_dict``: sphere,
cylinder, plane, mesh, generated part) and ``parse_artifact`` (the command line's ``sphere:radius=40,...``,
``mesh:path=PART.stl,pose=x;y;z;qx;qy;qz;qw,form_error=35``).

This module sits above ``artifacts`` (the analytic shapes), ``mesh`` (``MeshArtifact``) and ``generated_parts``
so that none of those three needs another's reader: the one place that knows every kind. Lengths in mm.
"""

from __future__ import annotations

import numpy as np

from .artifacts import Artifact, ArtifactSpecError, Cylinder, Plane, Sphere
from .generated_parts import apply_form_error, make_part
from .mesh import MeshArtifact
from .part_pose import PoseError, parse_pose7

__all__ = ["artifact_from_dict", "load_part_mesh", "mesh_from_dict", "parse_artifact", "parse_form_error", "parse_mesh"]


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
    """Parse ``sphere:radius=40[,center=x;y;z|center=fit]``, ``cylinder:radius=20[,center=..][,axis=x;y;z]``,
    ``plane[:point=..,normal=..]`` (mm) or ``mesh:path=PART.stl[,pose=x;y;z;qx;qy;qz;qw][,form_error=UM[:SIGMA]]``
    (``parse_mesh``). Returns the artifact and whether its centre is to be fitted (``center=fit``: centre fitted
    with the nominal radius fixed; never for a mesh). Raises ArtifactSpecError with the reason."""
    if not isinstance(spec, str) or not spec.strip():
        raise ArtifactSpecError("empty artifact specification")
    kind, _, rest = spec.strip().partition(":")
    kind = kind.strip().lower()
    opts: dict[str, str] = {}
    for part in filter(None, (p.strip() for p in rest.split(","))):
        key, eq, val = part.partition("=")
        if not eq:
            raise ArtifactSpecError(f"artifact option {part!r} in {spec!r} is not key=value (the numbers of one "
                                    "value are separated by ';', e.g. pose=0;0;0.012;0;0;0;1)")
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
    allowed = {"sphere": {"radius", "center"}, "cylinder": {"radius", "center", "axis"}, "plane": {"point", "normal"},
               "mesh": {"path", "pose", "form_error"}}
    if kind not in allowed:
        raise ArtifactSpecError(f"unknown artifact kind {kind!r} in {spec!r} (known: sphere, cylinder, plane, mesh)")
    unknown = set(opts) - allowed[kind]
    if unknown:
        raise ArtifactSpecError(f"unknown option(s) {sorted(unknown)} for {kind} in {spec!r}")
    if kind == "plane":
        return Plane(vec("point", (0.0, 0.0, 0.0)), vec("normal", (0.0, 0.0, 1.0))), False
    if kind == "mesh":
        return parse_mesh(opts, spec), False
    if "radius" not in opts:
        raise ArtifactSpecError(f"{kind} in {spec!r} needs radius=<mm>")
    try:
        radius = float(opts["radius"])
    except ValueError as e:
        raise ArtifactSpecError(f"radius={opts['radius']!r} in {spec!r} is not a number") from e
    if kind == "sphere":
        return Sphere(radius, vec("center", (0.0, 0.0, 0.0))), fit
    return Cylinder(radius, vec("center", (0.0, 0.0, 0.0)), vec("axis", (0.0, 1.0, 0.0))), fit


def parse_form_error(text: str, where: str = "form_error") -> tuple[float, float]:
    """``AMPLITUDE_UM[:SIGMA_MM]`` → (amplitude µm, σ mm; default 6, the generated parts' form error)."""
    amp, _, sig = text.partition(":")
    try:
        a, s = float(amp), float(sig) if sig.strip() else 6.0
    except ValueError as e:
        raise ArtifactSpecError(f"{where}={text!r}: expected AMPLITUDE_UM[:SIGMA_MM], e.g. 35 or 35:10") from e
    if not (np.isfinite(a) and np.isfinite(s) and s > 0):
        raise ArtifactSpecError(f"{where}={text!r}: the amplitude must be finite and σ a positive length (mm)")
    return a, s


def load_part_mesh(path: str, *, pose: np.ndarray | None = None, form_um: float = 0.0, form_sigma_mm: float = 6.0,
                   where: str = "") -> MeshArtifact:
    """A user's mesh file (STL, PLY, OBJ; millimetres, part frame) as the artifact: with the form error
    ``form_um`` (``generated_parts.apply_form_error``, truth kept in its ``to_dict``) and placed in the scan frame
    by ``pose`` (4, 4) mm. Raises ArtifactSpecError: file missing, unreadable or without triangles."""
    at = f" (in {where!r})" if where else ""
    try:
        mesh = MeshArtifact.from_file(path)
    except FileNotFoundError as e:
        raise ArtifactSpecError(f"mesh file {path!r} not found{at}") from e
    except ArtifactSpecError as e:
        raise ArtifactSpecError(f"{e}{at}") from e
    except ImportError as e:
        raise ArtifactSpecError(f"reading {path!r} needs open3d (the [train] extra; only binary STL is read "
                                f"without it){at}") from e
    except Exception as e:  # a damaged file: whatever the reader raised, said as the file's problem
        raise ArtifactSpecError(f"cannot read the mesh {path!r}{at}: {type(e).__name__}: {e}") from e
    if form_um:
        mesh = apply_form_error(mesh, form_um, form_sigma_mm)
    return mesh if pose is None or np.allclose(pose, np.eye(4)) else mesh.transformed(pose)


def parse_mesh(opts: dict[str, str], spec: str) -> MeshArtifact:
    """The options of ``mesh:path=PART.stl[,pose=x;y;z;qx;qy;qz;qw][,form_error=AMPLITUDE_UM[:SIGMA_MM]]``.

    - ``path``: the mesh file (STL, PLY, OBJ), millimetres, in the part's own frame (as the node's ``cad_mesh``);
      it may hold ``=`` but not ``,``.
    - ``pose``: part → scan frame, the 7 numbers of the node's ``cad_pose`` (x, y, z in metres, quaternion qx,
      qy, qz, qw; ``scan.part_pose``) separated by ``;`` (the spec's own separators are ``,`` and ``=``); default
      identity. The 12-number millimetre matrix of xmetro ≤ 0.5 is refused, with the 7 numbers to use.
    - ``form_error``: the part as manufactured, with the generated parts' known form error (``form_field``:
      +AMPLITUDE_UM bump, −0.6·AMPLITUDE_UM dip, along the part's +Z, centred on the mesh; SIGMA_MM scales the
      pattern, default 6). The truth stays in the artifact's ``to_dict`` (a bag's scan record)."""
    path = opts.get("path", "")
    if not path:
        raise ArtifactSpecError(f"mesh in {spec!r} needs path=PART.stl (STL, PLY or OBJ, millimetres)")
    try:
        pose = parse_pose7(opts.get("pose"), what="pose", sep=";")
    except PoseError as e:
        raise ArtifactSpecError(f"{e} (in {spec!r}; the 7 numbers separated by ';')") from e
    try:
        form_um, sigma = parse_form_error(opts["form_error"]) if "form_error" in opts else (0.0, 6.0)
    except ArtifactSpecError as e:
        raise ArtifactSpecError(f"{e} (in {spec!r})") from e
    return load_part_mesh(path, pose=pose, form_um=form_um, form_sigma_mm=sigma, where=spec)


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
        if src.get("form_um"):  # a manufactured part (apply_form_error): the same form error, rebuilt
            c = src.get("form_center_mm")
            base = apply_form_error(base, float(src["form_um"]), float(src.get("form_sigma_mm", 6.0)),
                                    center_mm=None if c is None else (float(c[0]), float(c[1])))
    elif "vertices" in d and "triangles" in d:
        base = MeshArtifact(np.asarray(d["vertices"]), np.asarray(d["triangles"]), name=str(d.get("name", "mesh")),
                            crease_deg=crease)
    else:
        raise ArtifactSpecError("a mesh artifact needs a source (part or path) or vertices and triangles")
    return base if np.allclose(t, np.eye(4)) else base.transformed(t)
