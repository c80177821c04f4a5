"""Base class of the virtual scanner's physical effects and the per-scan context they act on.

Every effect is a small, named, parameterised law that reads the noise-free geometry of the visible points (one
entry per point of the organized grid that returned light) and adds to it:

- a *systematic* displacement (deterministic in geometry + settings): it goes into ``Scan.expected_error``;
- a *random* displacement (noise, seeded): in the measured points only;
- a *drop* of points (no return), or a change of the shared signal / noise gain / intensity.

Displacements are vectors in the scan frame, mm. Most are depth errors along the laser ray ``d`` (the stripe
centroid moves on the sensor, so the triangulated point slides along the ray that lit it); lateral ones lie in the
laser plane, perpendicular to the ray.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from ..scan.artifacts import Artifact
from ..scan.geometry import HeadPose
from ..scan.scanner import ScannerModel, ScanSettings

__all__ = ["Effect", "EffectConfigError", "SimContext", "UnknownEffectError"]


class UnknownEffectError(ValueError):
    """An effect name (in ``effects=`` or the scanner YAML) that the simulator does not know."""


class EffectConfigError(ValueError):
    """An effect parameter that is unknown, not a finite number, or out of its allowed range."""


_UNSET = np.empty(0)


def _unset() -> np.ndarray:
    """Default of the per-point arrays of :class:`SimContext` that ``__post_init__`` fills."""
    return _UNSET


def _is_unset(a: np.ndarray | None) -> bool:
    return a is None or a is _UNSET


@dataclass
class SimContext:
    """Noise-free geometry of the M points that returned light, plus the accumulators the effects write to.

    Frames: all vectors in the scan frame; lengths mm; times ms unless named ``_s``.
    """

    artifact: Artifact
    scanner: ScannerModel
    settings: ScanSettings
    pose: HeadPose
    grid_shape: tuple[int, int]
    index: np.ndarray  # (M,) flat index of each point into the H x W grid
    origin: np.ndarray  # (M, 3) laser source position when the profile was taken
    d: np.ndarray  # (M, 3) unit ray direction (source → point)
    depth: np.ndarray  # (M,) distance source → true surface point
    p: np.ndarray  # (M, 3) true surface point
    n: np.ndarray  # (M, 3) outward unit normal
    V: np.ndarray  # (M, 3) unit vector point → camera
    standoff: np.ndarray  # (M,) distance along the laser axis (head -Z): the study's R_y
    u_ref: np.ndarray  # (M,) ray position along the line at the reference stand-off (head X), mm
    speed_mm_s: float  # head speed
    blur_mm: float  # head travel during one exposure
    keep: np.ndarray = field(default_factory=_unset)  # (M,) bool: False = no return
    sys: np.ndarray = field(default_factory=_unset)  # (M, 3) systematic displacement
    rand: np.ndarray = field(default_factory=_unset)  # (M, 3) random displacement
    snr_gain: np.ndarray = field(default_factory=_unset)  # (M,) multiplies the signal (exposure)
    noise_gain: np.ndarray = field(default_factory=_unset)  # (M,) multiplies SNR-limited random noise
    intensity: np.ndarray = field(default_factory=_unset)  # (M,) 0..1
    contributions: dict[str, np.ndarray] = field(default_factory=dict)  # name → (M, 3) systematic part
    noise_contributions: dict[str, np.ndarray] = field(default_factory=dict)  # name → (M, 3) random part
    # (M, 3, 3) covariance of the Gaussian random displacement, mm²
    rand_cov: np.ndarray = field(default_factory=_unset)
    stats: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        m = len(self.index)
        self.keep = np.ones(m, bool) if _is_unset(self.keep) else self.keep
        self.sys = np.zeros((m, 3)) if _is_unset(self.sys) else self.sys
        self.rand = np.zeros((m, 3)) if _is_unset(self.rand) else self.rand
        self.rand_cov = np.zeros((m, 3, 3)) if _is_unset(self.rand_cov) else self.rand_cov
        self.snr_gain = np.ones(m) if _is_unset(self.snr_gain) else self.snr_gain
        self.noise_gain = np.ones(m) if _is_unset(self.noise_gain) else self.noise_gain
        if _is_unset(self.intensity):
            self.intensity = np.clip(self.cos_inc, 0.0, 1.0)

    @property
    def m(self) -> int:
        return len(self.index)

    @property
    def cos_inc(self) -> np.ndarray:
        """Cosine of the laser incidence angle, N·L (L = -d), in (0, 1]."""
        return np.clip(-np.einsum("ij,ij->i", self.n, self.d), 1e-6, 1.0)

    @property
    def cos_view(self) -> np.ndarray:
        """Cosine of the camera viewing angle, N·V."""
        return np.clip(np.einsum("ij,ij->i", self.n, self.V), 1e-6, 1.0)

    @property
    def head_x(self) -> np.ndarray:
        return self.pose.rotation[:, 0]

    @property
    def head_y(self) -> np.ndarray:
        return self.pose.rotation[:, 1]

    def lateral_dir(self) -> np.ndarray:
        """(M, 3) unit vectors in the laser plane, perpendicular to the ray, pointing toward head +X."""
        ex = self.head_x
        v = ex[None, :] - np.outer(self.d @ ex, np.ones(3)) * self.d
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    def add_sys(self, name: str, disp: np.ndarray) -> None:
        self.sys += disp
        self.contributions[name] = self.contributions.get(name, 0) + disp

    def add_rand(self, name: str, disp: np.ndarray) -> None:
        self.rand += disp
        self.noise_contributions[name] = self.noise_contributions.get(name, 0) + disp

    def add_noise_cov(self, sigma: np.ndarray | float, direction: np.ndarray) -> None:
        """Declare the law of a Gaussian random displacement ``sigma`` (mm, (M,) or scalar) along the unit vectors
        ``direction`` (M, 3) or (3,): its covariance sigma² u uᵀ adds to ``rand_cov`` (effects draw independent
        streams, so covariances add). The simulator turns it into each point's true noise std."""
        sig = np.broadcast_to(np.asarray(sigma, np.float64), (self.m,))
        u = np.broadcast_to(np.asarray(direction, np.float64), (self.m, 3))
        self.rand_cov += (sig**2)[:, None, None] * u[:, :, None] * u[:, None, :]

    def along_ray(self, delta: np.ndarray) -> np.ndarray:
        """Displacement vectors (M, 3) for depth errors ``delta`` (mm, positive = farther from the source)."""
        return delta[:, None] * self.d


class Effect:
    """One physical effect: ``apply(ctx, rng)`` edits the context. Subclasses set the class attributes below.

    Class attributes:
        name: key in ``EFFECTS`` and in the scanner YAML ``effects:`` section.
        law: the law implemented, in words and symbols.
        source: literature the law and its magnitude come from.
        magnitude: typical size with the default parameters.
        drives: axes / study features the *systematic* part drives (the SHAP ground truth), or "noise only".
        defaults: parameter name → default value (numbers, or None where the scanner model supplies it).
        positive: parameters that must be > 0; nonnegative: parameters that must be >= 0.
    """

    name: ClassVar[str] = "effect"
    law: ClassVar[str] = ""
    source: ClassVar[str] = ""
    magnitude: ClassVar[str] = ""
    drives: ClassVar[str] = ""
    defaults: ClassVar[dict[str, float | None]] = {}
    positive: ClassVar[tuple[str, ...]] = ()
    nonnegative: ClassVar[tuple[str, ...]] = ()

    def __init__(self, **params: Any) -> None:
        unknown = set(params) - set(self.defaults)
        if unknown:
            raise EffectConfigError(
                f"effect {self.name!r}: unknown parameter(s) {sorted(unknown)} (known: {sorted(self.defaults)})"
            )
        merged = {**self.defaults, **params}
        for k, v in merged.items():
            if v is None and self.defaults[k] is None:
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise EffectConfigError(f"effect {self.name!r}: parameter {k} must be a finite number, got {v!r}")
            if k in self.positive and v <= 0:
                raise EffectConfigError(f"effect {self.name!r}: parameter {k} must be > 0, got {v!r}")
            if k in self.nonnegative and v < 0:
                raise EffectConfigError(f"effect {self.name!r}: parameter {k} must be >= 0, got {v!r}")
            merged[k] = float(v) if v is not None else None
        self.params: dict[str, float | None] = merged
        self.check()

    def p(self, name: str) -> float:
        """Parameter ``name`` as a number (EffectConfigError when it is unset: only parameters whose default is
        None may be, and the effect resolves those from the scanner model itself)."""
        v = self.params[name]
        if v is None:
            raise EffectConfigError(f"effect {self.name!r}: parameter {name} is unset")
        return v

    def values(self) -> dict[str, float]:
        """The parameters that are set, as numbers (unset ones, resolved from the scanner model, left out)."""
        return {k: v for k, v in self.params.items() if v is not None}

    def check(self) -> None:
        """Extra cross-parameter checks (raise EffectConfigError)."""

    def apply(self, ctx: SimContext, rng: np.random.Generator) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.params})"
