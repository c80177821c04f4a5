"""Scanner model (geometry + setting levels, from ``config/scanners/*.yaml``) and scan settings.

Units inside the package: mm, ms, per-mm densities. On ROS topics (ScannerSettings.msg): SI, i.e. points per
metre, profiles per metre, seconds. ``ScanSettings.to_si`` / ``from_si`` convert.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from .resources import config_path

__all__ = ["SETTING_NAMES", "ScanSettings", "ScannerModel", "SettingsError"]

SETTING_NAMES = ("lateral_density", "direction_density", "exposure_ms")


class SettingsError(ValueError):
    """Scan settings that are missing, not finite, not positive or out of the scanner's range."""


@dataclass(frozen=True)
class ScanSettings:
    """Settings of one scan.

    Attributes:
        lateral_density: points per mm along the laser line.
        direction_density: profiles per mm along the scan direction (inverse head speed per profile).
        exposure_ms: exposure time of each profile, ms.
    """

    lateral_density: float
    direction_density: float
    exposure_ms: float

    def validate(self, ranges: dict[str, tuple[float, float]] | None = None) -> ScanSettings:
        """Raise SettingsError naming the first bad value; return self when valid."""
        for name in SETTING_NAMES:
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise SettingsError(f"{name} must be a positive finite number, got {v!r}")
            if ranges and name in ranges:
                lo, hi = ranges[name]
                if not lo <= v <= hi:
                    raise SettingsError(f"{name} = {v:g} is outside the scanner's range [{lo:g}, {hi:g}]")
        return self

    def as_tuple(self) -> tuple[float, float, float]:
        return (self.lateral_density, self.direction_density, self.exposure_ms)

    def to_si(self) -> dict[str, float]:
        """Wire values: points per metre, profiles per metre, seconds."""
        return {
            "lateral_density": self.lateral_density * 1e3,
            "direction_density": self.direction_density * 1e3,
            "exposure_time": self.exposure_ms * 1e-3,
        }

    @classmethod
    def from_si(cls, lateral_density: float, direction_density: float, exposure_time: float) -> ScanSettings:
        """From wire values (per metre, per metre, seconds). Does not validate."""
        return cls(lateral_density * 1e-3, direction_density * 1e-3, exposure_time * 1e3)

    def label(self) -> str:
        return f"lat{self.lateral_density:g}_dir{self.direction_density:g}_exp{self.exposure_ms:g}"


@dataclass(frozen=True)
class ScannerModel:
    """Geometry and setting levels of a laser line scanner (see config/scanners/default.yaml)."""

    id: str
    standoff_mm: float
    baseline_mm: float
    fan_angle_deg: float
    depth_of_field_mm: tuple[float, float]
    settings_levels: dict[str, tuple[float, ...]]
    default_settings: ScanSettings
    settings_range: dict[str, tuple[float, float]]
    profile_rate_hz: float
    effects: dict[str, Any] = field(default_factory=dict)
    source: str = ""

    @property
    def triangulation_angle_deg(self) -> float:
        return math.degrees(math.atan2(self.baseline_mm, self.standoff_mm))

    @classmethod
    def load(cls, path: str | Path | None = None) -> ScannerModel:
        """Load a scanner YAML; ``None`` → the packaged default (config/scanners/default.yaml)."""
        p = Path(path) if path is not None else config_path("scanners/default.yaml")
        try:
            data = yaml.safe_load(p.read_text())
        except OSError as e:
            raise FileNotFoundError(f"scanner config {p} cannot be read: {e}") from e
        return cls.from_dict(data, source=p.name)

    @classmethod
    def from_dict(cls, d: dict[str, Any], source: str = "") -> ScannerModel:
        try:
            levels = {k: tuple(float(x) for x in d["settings_levels"][k]) for k in SETTING_NAMES}
            rng = {k: (float(d["settings_range"][k][0]), float(d["settings_range"][k][1])) for k in SETTING_NAMES}
            model = cls(
                id=str(d["id"]),
                standoff_mm=float(d["standoff_mm"]),
                baseline_mm=float(d["baseline_mm"]),
                fan_angle_deg=float(d["fan_angle_deg"]),
                depth_of_field_mm=(float(d["depth_of_field_mm"][0]), float(d["depth_of_field_mm"][1])),
                settings_levels=levels,
                default_settings=ScanSettings(**{k: float(d["default_settings"][k]) for k in SETTING_NAMES}),
                settings_range=rng,
                profile_rate_hz=float(d.get("profile_rate_hz", 2000.0)),
                effects=dict(d.get("effects") or {}),
                source=source,
            )
        except (KeyError, TypeError, IndexError) as e:
            raise ValueError(f"scanner config {source or '<dict>'} is missing or malformed: {e!r}") from e
        model.default_settings.validate(model.settings_range)
        return model

    def study_configurations(self) -> list[ScanSettings]:
        """The 27 (3 x 3 x 3) configurations of the study, in a fixed order (lateral, direction, exposure)."""
        lv = self.settings_levels
        return [
            ScanSettings(a, b, c)
            for a, b, c in itertools.product(lv["lateral_density"], lv["direction_density"], lv["exposure_ms"])
        ]

    def validate_settings(self, s: ScanSettings) -> ScanSettings:
        return s.validate(self.settings_range)
