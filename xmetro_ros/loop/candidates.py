"""Library of candidate explanatory variables for the residual (documented in docs/closed-loop.md).

Fields: every per-point field of the input, named ``field_<name>`` (the name the feature registry resolves, so a
selected field becomes a model feature the node reads from the PointCloud2). Fields named like an identity
(``pass``, ``profile``, ``pose``, ``*_id``) are identity candidates, held out inside their group; with profile data
(``hold_by="profile"``) an identity field names what profiles share (``pose``: the sensor position of repeats), is
not combined with the profile and is held out by whole profiles (``trace``: identities spanning groups).
Derived (when the input gives them): ``range`` (mm to the laser source / scanner), ``incidence_angle`` and
``viewing_angle`` (deg, nominal normal vs direction to source / camera), ``line_position`` (mm along the laser
line), ``scan_position`` (mm along the scan direction), ``x``/``y``/``z`` (mm), ``curvature`` (surface variation
of the 16 nearest neighbours, the point left out), ``density`` (points per mm², 8th neighbour),
``profile_identity`` and ``cloud_identity``; with profile data whose repeats share a ``pose`` field,
``pose_line_pattern`` (the pose × 0.5 mm cells along the line). A derived candidate duplicating a field is
dropped; candidates equivalent to a model feature (by name, or as a column of the model's features up to a
linear map or its magnitude, |r| ≥ 0.999) are flagged ``in_model`` (reported as controls, never selected).
When an artifact position was fitted, position-like candidates (``POSITION_LIKE``) are flagged ``confounded``
(traced, reported, never selected). ``SPECTRAL_NAMES`` also get the trace's spectral test.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .data import LoopData, LoopInputError

__all__ = ["DERIVED", "IDENTITY_FIELD_NAMES", "POSITION_LIKE", "SPECTRAL_NAMES", "CandidateInfo", "build_candidates",
           "has_fitted_positions"]

IDENTITY_FIELD_NAMES = {"pass", "pass_id", "profile", "profile_id", "pose", "pose_id", "cloud", "cloud_id", "id"}

# derived name → (unit, description, equivalent study feature or None)
DERIVED: dict[str, tuple[str, str, str | None]] = {
    "range": ("mm", "distance from the point to the laser source (scanner origin for TLS)", None),
    "incidence_angle": ("deg", "angle between the nominal normal and the direction to the laser source", "Inc"),
    "viewing_angle": ("deg", "angle between the nominal normal and the direction to the camera", "ViewAng"),
    "line_position": ("mm", "position along the laser line (head X / sensor x)", None),
    "scan_position": ("mm", "position along the scan direction (head Y)", None),
    "x": ("mm", "x coordinate in the artifact frame", None),
    "y": ("mm", "y coordinate in the artifact frame", None),
    "z": ("mm", "z coordinate in the artifact frame", None),
    "curvature": ("1", "local surface variation λ_min/Σλ of the 16 nearest neighbours", None),
    "density": ("1/mm²", "local point density from the 8th-neighbour distance", None),
    "profile_identity": ("id", "identity of each profile (per-profile / per-pose offset)", None),
    "cloud_identity": ("id", "identity of each cloud (per-cloud offset)", None),
    "pose_line_pattern": ("id", "identity of (sensor position, 0.5 mm cell along the line): an error shape that "
                          "repeats at a position (speckle, surface texture, a per-pose error that is no rigid offset)",
                          None),
}
#: Cell along the laser line of ``pose_line_pattern`` (mm): a few points of a profile, much shorter than a profile.
PATTERN_CELL_MM = 0.5
FIELD_DUPLICATES = {"line_position": "u", "scan_time": "t"}
#: Units of the fields our scans carry (t: s since the scan start; u, s: mm along the line / scan direction).
FIELD_UNITS = {"t": "s", "u": "mm", "s": "mm", "line": "id"}
#: Coordinates of the acquisition (time, positions): the trace also tests the residual spectrally over them.
SPECTRAL_NAMES = frozenset({"field_t", "field_time", "field_u", "field_s", "line_position", "scan_position",
                            "x", "y", "z"})
#: Positions on the artifact. With a fitted centre (per scan or per set), the fit's location error δc leaves an
#: error n·δc on every point, a smooth function of these variables that the same fit bias repeats from cloud to
#: cloud: such a candidate could "explain" it across held-out clouds. They are traced but never selected then.
POSITION_LIKE = frozenset({"x", "y", "z", "scan_position"})
FITTED_REASON = ("the artifact's position was fitted: a location error of the fit projects onto position-like "
                 "variables (known positions needed to tell it from the scanner)")


def has_fitted_positions(artifact: dict) -> bool:
    """True when the LoopData artifact description says a centre was fitted (``fit_center`` or a campaign
    placement with ``position: fitted``), in any group."""
    if not isinstance(artifact, dict):
        return False
    if artifact.get("fit_center") or artifact.get("position") == "fitted" or artifact.get("fitted_groups"):
        return True
    return any(has_fitted_positions(a) for a in artifact.get("per_group", []))


@dataclass(frozen=True)
class CandidateInfo:
    """A candidate explanatory variable: name, kind (continuous / identity), description, unit."""

    name: str
    kind: str  # "continuous" | "identity"
    unit: str
    description: str
    source: str  # "field" | "derived"
    in_model: bool
    confounded: str = ""  # why the candidate may not be selected (fitted positions), "" when it may


def _angle(n: np.ndarray, d: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", n, d), -1.0, 1.0)))


def _local_shape(points: np.ndarray, group: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Curvature (surface variation) and density per point, neighbours taken inside each group."""
    curv = np.zeros(len(points))
    dens = np.zeros(len(points))
    for g in np.unique(group):
        idx = np.flatnonzero(group == g)
        p = points[idx]
        k = min(17, len(p))
        if k < 5:
            continue
        tree = cKDTree(p)
        dist, nn = tree.query(p, k=k)
        # Leave the point itself out: its own noise must not enter its own candidate value.
        dist, nn = dist[:, 1:], nn[:, 1:]
        k -= 1
        nb = p[nn] - p[nn].mean(axis=1, keepdims=True)
        cov = np.einsum("nki,nkj->nij", nb, nb) / k
        ev = np.linalg.eigvalsh(cov)
        curv[idx] = ev[:, 0] / np.maximum(ev.sum(axis=1), 1e-18)
        r = dist[:, min(8, k - 1)]
        dens[idx] = min(8, k - 1) / (np.pi * np.maximum(r, 1e-9) ** 2)
    return curv, dens


def build_candidates(
    data: LoopData, include: list[str] | None = None, exclude: tuple[str, ...] = ()
) -> tuple[dict[str, np.ndarray], dict[str, CandidateInfo]]:
    """Candidate values (name → (N,) float) and their descriptions for ``data``.

    Args:
        include: restrict to these names (``field_<name>`` or a derived name); a name the input cannot give raises
            LoopInputError naming it (e.g. ``field_intensity`` on a file without intensity).
        exclude: names to leave out (e.g. variables already added in an earlier iteration).
    """
    vals: dict[str, np.ndarray] = {}
    info: dict[str, CandidateInfo] = {}
    feats = set(data.feature_names)

    def add(name: str, v: np.ndarray, kind: str, unit: str, desc: str, source: str, equiv: str | None) -> None:
        vals[name] = np.asarray(v, dtype=float)
        in_model = (name in feats or (equiv in feats if equiv else False)
                    or (kind == "continuous" and _duplicates_a_feature(vals[name], data.X)))
        conf = FITTED_REASON if (fitted and name in POSITION_LIKE) else ""
        info[name] = CandidateInfo(name, kind, unit, desc, source, in_model, conf)

    want = set(include) if include is not None else None
    fitted = has_fitted_positions(data.artifact)

    def wanted(name: str) -> bool:
        return (want is None or name in want) and name not in exclude

    for fname, arr in data.fields.items():
        if not wanted(f"field_{fname}"):
            continue
        kind = "identity" if (fname.lower() in IDENTITY_FIELD_NAMES or fname.lower().endswith("_id")) else "continuous"
        v = np.asarray(arr, dtype=float)
        if kind == "identity" and data.hold_by != "profile":
            # An identity lives inside its cloud. A profile has one value of it (combined, it would be the profile):
            # with profile data it names what the profiles share (the sensor position of repeats).
            v = _combine(data.group, v)
        add(f"field_{fname}", v, kind, FIELD_UNITS.get(fname, ""), f"input field {fname!r}", "field", None)

    g = data.geometry
    if "source_distance" in g and wanted("range"):
        add("range", g["source_distance"], "continuous", *DERIVED["range"][:2], "derived", None)
    if "L" in g and wanted("incidence_angle"):
        add("incidence_angle", _angle(data.normals, g["L"]), "continuous", *DERIVED["incidence_angle"][:2],
            "derived", "Inc")
    if "V" in g and wanted("viewing_angle"):
        add("viewing_angle", _angle(data.normals, g["V"]), "continuous", *DERIVED["viewing_angle"][:2],
            "derived", "ViewAng")
    if "u" in g and "u" not in data.fields and wanted("line_position"):
        add("line_position", g["u"], "continuous", *DERIVED["line_position"][:2], "derived", None)
    if "s" in g and wanted("scan_position"):
        add("scan_position", g["s"], "continuous", *DERIVED["scan_position"][:2], "derived", None)
    for i, ax in enumerate("xyz"):
        if wanted(ax):
            add(ax, data.points[:, i], "continuous", *DERIVED[ax][:2], "derived", None)
    if wanted("curvature") or wanted("density"):
        curv, dens = _local_shape(data.points, data.group)
        if wanted("curvature"):
            add("curvature", curv, "continuous", *DERIVED["curvature"][:2], "derived", None)
        if wanted("density"):
            add("density", dens, "continuous", *DERIVED["density"][:2], "derived", None)
    if wanted("profile_identity"):
        if data.hold_by == "profile":
            add("profile_identity", data.group, "identity", *DERIVED["profile_identity"][:2], "derived", None)
        elif "line" in data.fields:
            add("profile_identity", _combine(data.group, data.fields["line"]), "identity",
                *DERIVED["profile_identity"][:2], "derived", None)
    if wanted("pose_line_pattern") and data.hold_by == "profile" and "pose" in data.fields and "u" in g:
        # Repeats of one sensor position (field ``pose``) see the same error shape along the line; the per-profile
        # fit of the nominal absorbs each profile's rigid offset, so only a cell-wise identity can show it.
        cell = np.floor(np.asarray(g["u"], dtype=float) / PATTERN_CELL_MM)
        add("pose_line_pattern", _combine(np.asarray(data.fields["pose"], dtype=float), cell), "identity",
            *DERIVED["pose_line_pattern"][:2], "derived", None)
    if wanted("cloud_identity") and data.hold_by == "cloud" and len(data.groups) > 1:
        add("cloud_identity", data.group, "identity", *DERIVED["cloud_identity"][:2], "derived", None)

    if include is not None:
        missing = [n for n in include if n not in vals]
        if missing:
            avail = sorted(vals)
            raise LoopInputError(f"candidate(s) {missing} are not available in this input (available: {avail})")
    for name in exclude:
        vals.pop(name, None)
        info.pop(name, None)
    return vals, info


def _duplicates_a_feature(v: np.ndarray, X: np.ndarray, r_min: float = 0.999) -> bool:
    """True when ``v`` is (up to a linear map, or of the feature's magnitude) a column of the model's features X:
    e.g. a profile's line position is its feature ``u``, its incidence the magnitude of ``inc_plane``. Such a
    candidate is a control, never a new variable (re-adding a feature only re-fits the model)."""
    v = np.asarray(v, dtype=float)
    if len(v) < 3 or np.std(v) == 0:
        return False
    for j in range(X.shape[1]):
        f = np.asarray(X[:, j], dtype=float)
        for g in (f, np.abs(f)):
            if np.std(g) > 0 and abs(np.corrcoef(v, g)[0, 1]) >= r_min:
                return True
    return False


def _combine(group: np.ndarray, v: np.ndarray) -> np.ndarray:
    """One code per (group, value) pair."""
    keys = np.stack([np.asarray(group, dtype=float), np.asarray(v, dtype=float)], axis=1)
    _, codes = np.unique(keys, axis=0, return_inverse=True)
    return codes.reshape(-1).astype(float)
