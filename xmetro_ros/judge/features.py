"""Per-point features (the study's §3.4) through a registry: a model's feature list is data, not code.

Each :class:`Feature` has a name, a unit, a formula (text, for docs and model cards), the inputs it needs
(``"normals"``, ``"L"``, ``"V"``, ``"standoff"``, ``"settings"``, ``"points"``, ... or ``"field:<name>"`` for a
per-point field of the cloud) and a function ``func(ctx) -> (M,) array or scalar``. ``compute_features`` fills one
preallocated (M, F) array; shared intermediates (N·L, N·V, |N×L|) are computed once per context.

Vectors (scan frame, unit): N outward surface normal, L point → laser source, V point → camera.
The study's eq. 4-5 write Inc = cos(N·L / |N||L|) and ViewAng = cos(N·V / ...); we use the cosine similarity
itself (N·L, N·V), which is what the text describes ("the cosine of the incidence angle"). See docs/features.md.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..compute.threads import NUMPY_BLOCK_THREADS, block_bounds, budget, parallel_for
from ..scan.geometry import HeadPose, camera_vector, point_geometry
from ..scan.scanner import ScannerModel, ScanSettings

__all__ = [
    "REGISTRY",
    "STUDY_FEATURES",
    "Feature",
    "FeatureContext",
    "FeatureError",
    "FeatureRegistry",
    "MissingFieldError",
    "UnknownFeatureError",
    "compute_features",
    "required_fields",
]

FIELD_PREFIX = "field_"


class FeatureError(ValueError):
    """A feature that cannot be registered or computed (bad definition, inconsistent context)."""


class UnknownFeatureError(KeyError, FeatureError):
    """A feature name the registry does not know (and that is not ``field_<name>``)."""

    def __str__(self) -> str:  # KeyError would quote the whole message
        return str(self.args[0]) if self.args else "unknown feature"


class MissingFieldError(FeatureError):
    """A feature needs a per-point field that the cloud does not carry."""

    def __init__(self, field_name: str, feature: str, available: Iterable[str] = ()):
        self.field_name = field_name
        self.feature = feature
        avail = ", ".join(sorted(available)) or "none"
        super().__init__(f"feature {feature!r} needs the per-point field {field_name!r}, not in the cloud "
                         f"(fields: {avail})")


@dataclass(frozen=True)
class Feature:
    """One per-point feature.

    Attributes:
        name: unique name (model cards list these).
        unit: unit of the value ("1", "mm", "deg", "/mm", "ms", ...).
        formula: human-readable definition.
        inputs: what it reads: context attributes ("normals", "L", "V", "standoff", "source_distance", "points",
            "u", "s", "settings", "normal_quality") or "field:<name>" for a per-point field.
        func: ``func(ctx) -> (M,) array or scalar`` (broadcast over the points).
    """

    name: str
    unit: str
    formula: str
    inputs: tuple[str, ...]
    func: Callable[[FeatureContext], Any]

    @property
    def fields(self) -> tuple[str, ...]:
        """Per-point fields this feature needs."""
        return tuple(i.split(":", 1)[1] for i in self.inputs if i.startswith("field:"))


class FeatureRegistry:
    """Name → Feature. ``get`` also resolves ``field_<name>`` to the raw per-point field ``<name>``."""

    def __init__(self) -> None:
        self._features: dict[str, Feature] = {}

    def register(
        self,
        feature: Feature | str,
        unit: str | None = None,
        formula: str = "",
        inputs: Sequence[str] = (),
        func: Callable[[FeatureContext], Any] | None = None,
        *,
        replace_existing: bool = False,
    ) -> Feature:
        """Register a Feature (or build one from name, unit, formula, inputs, func). A name already registered →
        FeatureError unless ``replace_existing``. Returns the registered feature."""
        if not isinstance(feature, Feature):
            if func is None or unit is None:
                raise FeatureError(f"feature {feature!r}: unit and func are required")
            feature = Feature(str(feature), unit, formula, tuple(inputs), func)
        if not feature.name or not isinstance(feature.name, str):
            raise FeatureError(f"feature name must be a non-empty string, got {feature.name!r}")
        if not callable(feature.func):
            raise FeatureError(f"feature {feature.name!r}: func is not callable")
        if feature.name in self._features and not replace_existing:
            raise FeatureError(f"feature {feature.name!r} is already registered (pass replace_existing=True)")
        self._features[feature.name] = feature
        return feature

    def unregister(self, name: str) -> None:
        self._features.pop(name, None)

    def get(self, name: str) -> Feature:
        f = self._features.get(name)
        if f is not None:
            return f
        if isinstance(name, str) and name.startswith(FIELD_PREFIX) and len(name) > len(FIELD_PREFIX):
            fname = name[len(FIELD_PREFIX):]
            def field_value(ctx: FeatureContext, _f: str = fname, _n: str = name) -> np.ndarray:
                return ctx.field(_f, _n)

            return Feature(name, "field", f"per-point field '{fname}' of the cloud", (f"field:{fname}",), field_value)
        raise UnknownFeatureError(
            f"unknown feature {name!r} (registered: {', '.join(self._features)}; or field_<name> for a cloud field)"
        )

    def __contains__(self, name: str) -> bool:
        try:
            self.get(name)
        except UnknownFeatureError:
            return False
        return True

    def names(self) -> list[str]:
        return list(self._features)

    def describe(self, names: Sequence[str] | None = None) -> list[dict[str, Any]]:
        """[{name, unit, formula, inputs}] for model cards and docs."""
        return [
            {"name": f.name, "unit": f.unit, "formula": f.formula, "inputs": list(f.inputs)}
            for f in (self.get(n) for n in (names if names is not None else self.names()))
        ]


@dataclass
class FeatureContext:
    """Everything per-point features are computed from (scan frame, mm; float32 on the hot path).

    Attributes:
        normals: (M, 3) unit outward normals N.
        L, V: (M, 3) unit vectors toward the laser source / camera.
        standoff: (M,) the study's R_y (= 90 − Z in the study's set-up), mm.
        source_distance: (M,) distance to the laser source, mm.
        settings: the scan settings (None for measured data that declare none: settings features then fail).
        fields: per-point fields {name: (M,)}.
        points: (M, 3) points, mm.
        u, s: (M,) position along the laser line / scan direction in the head frame, mm.
        normal_quality: (M,) normal quality in [0, 1] (optional).
    """

    normals: np.ndarray
    L: np.ndarray
    V: np.ndarray
    standoff: np.ndarray
    source_distance: np.ndarray
    settings: ScanSettings | None
    fields: dict[str, np.ndarray] = field(default_factory=dict)
    points: np.ndarray | None = None
    u: np.ndarray | None = None
    s: np.ndarray | None = None
    normal_quality: np.ndarray | None = None
    camera_mm: tuple[float, float, float] | None = None
    _cache: dict[str, np.ndarray] = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        m = np.shape(self.normals)[0] if np.ndim(self.normals) == 2 else -1
        for name in ("normals", "L", "V"):
            shape = np.shape(getattr(self, name))
            if shape != (m, 3):
                raise FeatureError(f"{name} must have shape (M, 3) matching normals, got {shape}")
        for name in ("standoff", "source_distance"):
            if np.shape(getattr(self, name)) != (m,):
                raise FeatureError(f"{name} must have shape ({m},), got {np.shape(getattr(self, name))}")
        for k, v in self.fields.items():
            if np.shape(v) != (m,):
                raise FeatureError(f"field {k!r} must have shape ({m},), got {np.shape(v)}")

    def __len__(self) -> int:
        return len(self.normals)

    @classmethod
    def from_prepared(cls, prepared: Any) -> FeatureContext:
        """From a ``preprocess.Prepared`` (normals, geometry, settings, fields of the kept points)."""
        g = prepared.geometry
        return cls(
            normals=prepared.normals,
            L=g.L,
            V=g.V,
            standoff=g.standoff,
            source_distance=g.source_distance,
            settings=prepared.settings,
            fields=dict(prepared.fields),
            points=prepared.points,
            u=g.u,
            s=g.s,
            normal_quality=prepared.normal_quality,
            camera_mm=prepared.scanner.camera_mm,
        )

    def with_pose(self, pose: HeadPose, scanner: ScannerModel | float | Any = None) -> FeatureContext:
        """The same points and normals seen from another head pose (L, V, standoff, u, s recomputed; normals are
        NOT re-oriented). ``scanner``: ScannerModel, camera position (head frame, mm) or baseline in mm (default:
        this context's camera)."""
        if self.points is None:
            raise FeatureError("with_pose needs the context's points")
        if isinstance(scanner, ScannerModel):
            camera = scanner.camera_mm
        elif scanner is not None:
            camera = camera_vector(scanner)
        elif self.camera_mm is not None:
            camera = self.camera_mm
        else:
            raise FeatureError("with_pose needs a scanner (or camera_mm) to place the camera")
        g = point_geometry(self.points, pose, camera, dtype=self.normals.dtype.type)
        return replace(self, L=g.L, V=g.V, standoff=g.standoff, source_distance=g.source_distance, u=g.u, s=g.s,
                       camera_mm=camera, _cache={})

    def subset(self, rows: np.ndarray | slice) -> FeatureContext:
        """The context restricted to ``rows`` (indices, boolean mask or a slice: views) of its points."""
        def cut(v: Any) -> Any:
            return None if v is None else v[rows]

        return replace(self, normals=self.normals[rows], L=self.L[rows], V=self.V[rows], standoff=self.standoff[rows],
                       source_distance=self.source_distance[rows], fields={k: v[rows] for k, v in self.fields.items()},
                       points=cut(self.points), u=cut(self.u), s=cut(self.s), normal_quality=cut(self.normal_quality),
                       _cache={})

    def with_settings(self, settings: ScanSettings) -> FeatureContext:
        """The same geometry under other scan settings."""
        return replace(self, settings=settings, _cache={})

    def field(self, name: str, feature: str | None = None) -> np.ndarray:
        """Per-point field ``name``; MissingFieldError naming it when absent."""
        try:
            return self.fields[name]
        except KeyError:
            raise MissingFieldError(name, feature or f"{FIELD_PREFIX}{name}", self.fields) from None

    def cached(self, key: str, fn: Callable[[], np.ndarray]) -> np.ndarray:
        """Shared intermediate ``key`` computed once per context."""
        v = self._cache.get(key)
        if v is None:
            v = self._cache[key] = fn()
        return v

    def check_normals(self) -> np.ndarray:
        """Raise FeatureError when a normal is not finite or not of unit length (±1e-3): degenerate normals would
        silently give Inc = 0, ang = 0. Returns the squared norms."""
        n = self.normals
        nn = n[:, 0] * n[:, 0] + n[:, 1] * n[:, 1] + n[:, 2] * n[:, 2]
        bad = ~(np.abs(nn - 1) <= 2e-3)  # NaN-safe
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise FeatureError(f"{int(bad.sum())} normal(s) are degenerate (not finite or not unit length), e.g. "
                               f"point {i}: {n[i].tolist()}")
        return nn

    # shared intermediates
    def n_dot_l(self) -> np.ndarray:
        return self.cached("NdotL", lambda: np.einsum("ij,ij->i", self.normals, self.L))

    def n_dot_v(self) -> np.ndarray:
        return self.cached("NdotV", lambda: np.einsum("ij,ij->i", self.normals, self.V))

    def n_cross_l_norm(self) -> np.ndarray:
        """|N × L| = sqrt(|N|²|L|² − (N·L)²) (Lagrange's identity; cheaper than the cross product)."""

        def f() -> np.ndarray:
            n, lv = self.normals, self.L
            nn = n[:, 0] * n[:, 0] + n[:, 1] * n[:, 1] + n[:, 2] * n[:, 2]
            ll = lv[:, 0] * lv[:, 0] + lv[:, 1] * lv[:, 1] + lv[:, 2] * lv[:, 2]
            nn *= ll
            c = self.n_dot_l()
            nn -= c * c
            np.maximum(nn, 0, out=nn)
            return np.sqrt(nn, out=nn)

        return self.cached("|NxL|", f)


def _col(a: str, j: int) -> Callable[[FeatureContext], np.ndarray]:
    return lambda ctx: getattr(ctx, a)[:, j]


def _diff(a: str, j: int) -> Callable[[FeatureContext], np.ndarray]:
    return lambda ctx: ctx.normals[:, j] - getattr(ctx, a)[:, j]


def _ang(ctx: FeatureContext) -> np.ndarray:
    a = np.arctan2(ctx.n_cross_l_norm(), ctx.n_dot_l())
    return np.multiply(a, np.float32(180 / np.pi) if a.dtype == np.float32 else 180 / np.pi, out=a)


REGISTRY = FeatureRegistry()

def _settings(ctx: FeatureContext) -> ScanSettings:
    """The context's scan settings; FeatureError when it has none (measured data)."""
    if ctx.settings is None:
        raise FeatureError("this feature needs the scan settings, which this data does not declare")
    return ctx.settings

_STUDY: list[Feature] = [
    Feature("lateral_density", "/mm", "scan setting: points per mm along the laser line", ("settings",),
            lambda ctx: _settings(ctx).lateral_density),
    Feature("direction_density", "/mm", "scan setting: profiles per mm along the scan direction", ("settings",),
            lambda ctx: _settings(ctx).direction_density),
    Feature("exposure_time", "ms", "scan setting: exposure time of each profile", ("settings",),
            lambda ctx: _settings(ctx).exposure_ms),
    *[Feature(f"N_{a}", "1", f"N_{a}: outward unit surface normal (eq. 1)", ("normals",), _col("normals", j))
      for j, a in enumerate("xyz")],
    *[Feature(f"ori_{a}", "1", f"(N - L)_{a} (eq. 2)", ("normals", "L"), _diff("L", j)) for j, a in enumerate("xyz")],
    Feature("oriCMOS_y", "1", "(N - V)_y (eq. 3; x, z equal ori_x, ori_z by design)", ("normals", "V"), _diff("V", 1)),
    Feature("Inc", "1", "N·L/(|N||L|): cosine of the incidence angle (eq. 4, cosine similarity)", ("normals", "L"),
            lambda ctx: ctx.n_dot_l()),
    Feature("ViewAng", "1", "N·V/(|N||V|): cosine of the viewing angle (eq. 5, cosine similarity)", ("normals", "V"),
            lambda ctx: ctx.n_dot_v()),
    Feature("R_y", "mm", "stand-off along the laser axis to the source; = 90 - Z in the study's set-up (eq. 6)",
            ("standoff",), lambda ctx: ctx.standoff),
    Feature("ang", "deg", "atan2d(|N x L|, N·L): angle between laser and surface orientation (eq. 7)",
            ("normals", "L"), lambda ctx: _ang(ctx)),
]
for _f in _STUDY:
    REGISTRY.register(_f)

#: The study's 14 input features, in order.
STUDY_FEATURES: list[str] = [f.name for f in _STUDY]


def required_fields(names: Sequence[str], registry: FeatureRegistry | None = None) -> set[str]:
    """Per-point fields the features ``names`` need (UnknownFeatureError on an unknown name)."""
    reg = registry or REGISTRY
    out: set[str] = set()
    for n in names:
        out.update(reg.get(n).fields)
    return out


#: Rows per block of :func:`compute_features` at the least (smaller blocks cost more in hand-offs than they save).
_MIN_BLOCK_ROWS = 8192


def compute_features(
    names: Sequence[str],
    ctx: FeatureContext,
    dtype: type = np.float32,
    registry: FeatureRegistry | None = None,
    out: np.ndarray | None = None,
    threads: int | None = None,
) -> np.ndarray:
    """Features ``names`` for every point of ``ctx``: (M, F) array of ``dtype`` (columns in the order of names).

    ``threads``: row blocks computed side by side (default: the calling thread's budget,
    ``compute.threads.budget``; at most ``NUMPY_BLOCK_THREADS``); every feature is an element-wise function of its
    row, so the blocks give the same bits as one pass. The shared intermediates the blocks computed (N·L, N·V,
    |N × L|) are joined into ``ctx``'s cache for the caller (the flags use them).

    Raises UnknownFeatureError (unknown name), MissingFieldError (a needed per-point field is absent; checked
    before computing anything) or FeatureError (a feature function returning the wrong shape)."""
    reg = registry or REGISTRY
    if isinstance(names, str):
        raise FeatureError("names must be a list of feature names, not a string")
    feats = [reg.get(n) for n in names]
    for f in feats:
        for fld in f.fields:
            if fld not in ctx.fields:
                raise MissingFieldError(fld, f.name, ctx.fields)
    m = len(ctx)
    if out is None:
        out = np.empty((m, len(feats)), dtype=dtype)
    elif out.shape != (m, len(feats)):
        raise FeatureError(f"out must have shape {(m, len(feats))}, got {out.shape}")
    normals = any("normals" in f.inputs for f in feats)
    threads = min(budget() if threads is None else int(threads), NUMPY_BLOCK_THREADS)
    bounds = block_bounds(m, threads, _MIN_BLOCK_ROWS)
    if len(bounds) == 1:
        if normals:
            ctx.cached("normals_checked", ctx.check_normals)
        _fill(feats, ctx, out)
        return out
    subs = [ctx.subset(slice(lo, hi)) for lo, hi in bounds]

    def block(i: int) -> None:
        if normals:
            subs[i].check_normals()
        _fill(feats, subs[i], out[bounds[i][0] : bounds[i][1]])

    try:
        parallel_for(block, len(bounds), threads)
    except FeatureError:
        if normals:
            ctx.check_normals()  # the message names the cloud's point, not a block's
        raise
    for key in subs[0]._cache:
        parts = [sub._cache[key] for sub in subs if key in sub._cache]
        if len(parts) == len(subs) and all(np.ndim(p) == 1 for p in parts):
            ctx._cache.setdefault(key, np.concatenate(parts))
    return out


def _fill(feats: list[Feature], ctx: FeatureContext, out: np.ndarray) -> None:
    """Write each feature of ``ctx``'s rows into its column of ``out`` (M, F). The columns go to a contiguous
    (F, M) block first and into ``out`` in one transposed copy: a column written straight into the row-major ``out``
    touches a cache line per row, F times over (7.4 against 3-6 ms for 167k × 15 here; the same casts, the same
    bits)."""
    m = len(ctx)
    cols = np.empty((len(feats), m), dtype=out.dtype)
    for j, f in enumerate(feats):
        v = f.func(ctx)
        if np.ndim(v) == 0 or np.shape(v) == (m,):
            cols[j] = v
        else:
            raise FeatureError(f"feature {f.name!r} returned shape {np.shape(v)}, expected ({m},) or a scalar")
    out[...] = cols.T
