"""The loop's table: every point of the input with its ground-truth error, the current model's features, its
per-point fields, its geometry and the unit it is held out by (cloud or profile). Lengths mm, angles deg, time s.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["LoopData", "LoopInputError"]


class LoopInputError(ValueError):
    """Input the loop cannot work with: missing / unreadable files, too few points or groups, bad candidates."""


@dataclass
class LoopData:
    """Per-point table of the loop (N points).

    Attributes:
        points: (N, 3) measured points, mm, in the frame of the nominal artifact.
        normals: (N, 3) outward unit normals of the nominal artifact at the projections of the points.
        errors: (N, 3) ground truth nominal − measured per axis, mm (artifact fitted as configured).
        X: (N, F) float32 features of the current model, named by ``feature_names``.
        fields: per-point input fields (intensity, line, t, u, ...), name → (N,).
        group: (N,) int unit of holding out (a cloud, or a profile for profile data).
        order: (N,) int acquisition order of the point inside its group.
        geometry: optional per-point geometry: ``source_distance`` (mm), ``L``/``V`` (N, 3) unit vectors toward the
            source / camera, ``u`` (mm along the laser line), ``s`` (mm along the scan direction).
        group_names: name of each group id (file or scan label).
        source: "scans" | "nist" | "atc5" | ...
        hold_by: "cloud" or "profile" (what a group is).
        artifact: nominal artifact description (``to_dict``) and fit summary.
    """

    points: np.ndarray
    normals: np.ndarray
    errors: np.ndarray
    X: np.ndarray
    feature_names: list[str]
    fields: dict[str, np.ndarray]
    group: np.ndarray
    order: np.ndarray
    geometry: dict[str, np.ndarray] = field(default_factory=dict)
    group_names: list[str] = field(default_factory=list)
    source: str = ""
    hold_by: str = "cloud"
    artifact: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = len(self.points)
        if n == 0:
            raise LoopInputError("no points in the input")
        for name, arr in [("normals", self.normals), ("errors", self.errors), ("X", self.X),
                          ("group", self.group), ("order", self.order)]:
            if len(arr) != n:
                raise ValueError(f"LoopData.{name} has {len(arr)} rows, expected {n}")
        for name, arr in self.fields.items():
            if np.shape(arr) != (n,):
                raise ValueError(f"field {name!r} has shape {np.shape(arr)}, expected ({n},)")
        if self.X.ndim != 2 or self.X.shape[1] != len(self.feature_names):
            raise ValueError("X columns must match feature_names")

    @property
    def n(self) -> int:
        return len(self.points)

    @property
    def groups(self) -> np.ndarray:
        return np.unique(self.group)

    def subset(self, mask: np.ndarray) -> LoopData:
        """Rows selected by a boolean mask or an index array."""
        return LoopData(
            points=self.points[mask], normals=self.normals[mask], errors=self.errors[mask], X=self.X[mask],
            feature_names=list(self.feature_names), fields={k: v[mask] for k, v in self.fields.items()},
            group=self.group[mask], order=self.order[mask],
            geometry={k: v[mask] for k, v in self.geometry.items()}, group_names=list(self.group_names),
            source=self.source, hold_by=self.hold_by, artifact=dict(self.artifact),
        )

    @staticmethod
    def concat(parts: list[LoopData]) -> LoopData:
        """Stack tables with the same features; group ids are renumbered to stay unique."""
        if not parts:
            raise LoopInputError("no input tables")
        names = parts[0].feature_names
        if any(p.feature_names != names for p in parts):
            raise LoopInputError("inputs have different feature sets; give inputs of one kind per loop run")
        # The first part's order, not a set's: the trace seeds each candidate by its position, and a set of str
        # iterates in an order that changes with the process's hash seed (parts built on Dask workers).
        common = [k for k in parts[0].fields if all(k in p.fields for p in parts[1:])]
        gcommon = [k for k in parts[0].geometry if all(k in p.geometry for p in parts[1:])]
        groups, gnames, off = [], [], 0
        for p in parts:
            ug, inv = np.unique(p.group, return_inverse=True)
            groups.append(inv + off)
            gnames += [p.group_names[g] if g < len(p.group_names) else f"group{g}" for g in ug]
            off += len(ug)
        return LoopData(
            points=np.concatenate([p.points for p in parts]), normals=np.concatenate([p.normals for p in parts]),
            errors=np.concatenate([p.errors for p in parts]), X=np.concatenate([p.X for p in parts]),
            feature_names=list(names), fields={k: np.concatenate([p.fields[k] for p in parts]) for k in common},
            group=np.concatenate(groups), order=np.concatenate([p.order for p in parts]),
            geometry={k: np.concatenate([p.geometry[k] for p in parts]) for k in gcommon}, group_names=gnames,
            source=parts[0].source, hold_by=parts[0].hold_by, artifact=_merge_artifacts([p.artifact for p in parts]),
        )


def _merge_artifacts(arts: list[dict]) -> dict:
    """One description when all parts share the artifact, else the list per group."""
    if all(a == arts[0] for a in arts):
        return dict(arts[0])
    return {"per_group": arts}
