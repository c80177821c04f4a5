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
    """Geometry and setting levels of a laser line scanner (see config/scanners/default.yaml).

    Two ways to describe the geometry in the YAML (docs/simulator.md, "Scanner description"):

    - the model's own terms: ``standoff_mm`` (laser source → reference point on the laser axis), ``baseline_mm``
      (camera along head +Y at the laser's height) or ``camera_mm`` (camera position in the head frame),
      ``fan_angle_deg``, ``depth_of_field_mm`` (near, far along the laser axis from the source);
    - data-sheet terms (a real device): ``measuring_range_mm`` (near, far: distances from the sensor-frame origin
      along the laser axis), ``field_of_view_mm`` (line length at near and at far), ``triangulation_angle_deg``
      and ``camera_side`` (+y / -y; optional ``camera_height_mm`` along the laser direction), and optionally
      ``sensor_frame.axes`` (the sensor's x, y, z axes in head-frame coordinates). The laser source is where the
      fan's edges meet; the sensor-frame origin lies on the laser axis where the measuring range is counted
      from; the reference stand-off is the middle of the measuring range.

    ``settings_levels`` are optional (a data sheet does not give them): ``study_configurations`` then needs the
    levels of a campaign (:meth:`with_levels`).
    """

    id: str
    standoff_mm: float
    camera_mm: tuple[float, float, float]
    fan_angle_deg: float
    depth_of_field_mm: tuple[float, float]
    settings_levels: dict[str, tuple[float, ...]] | None
    default_settings: ScanSettings
    settings_range: dict[str, tuple[float, float]]
    profile_rate_hz: float
    effects: dict[str, Any] = field(default_factory=dict)
    source: str = ""
    serial: str = ""
    description: str = ""
    sensor_origin_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    sensor_axes: tuple[tuple[float, float, float], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))

    @property
    def baseline_mm(self) -> float:
        """Camera offset from the laser source across the laser plane (|head y| of the camera), mm."""
        return abs(self.camera_mm[1])

    @property
    def triangulation_angle_deg(self) -> float:
        """Angle between the laser axis and the camera's line of sight to the reference point, degrees."""
        cx, cy, cz = self.camera_mm
        return math.degrees(math.atan2(math.hypot(cx, cy), self.standoff_mm + cz))

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
        """From the YAML's mapping (either description, see the class docstring). ValueError naming what is wrong."""
        where = source or "<dict>"
        try:
            geom = _datasheet_geometry(d, where) if "measuring_range_mm" in d else _model_geometry(d, where)
            levels = None
            if d.get("settings_levels") is not None:
                levels = {k: tuple(float(x) for x in d["settings_levels"][k]) for k in SETTING_NAMES}
            rng = {k: (float(d["settings_range"][k][0]), float(d["settings_range"][k][1])) for k in SETTING_NAMES}
            model = cls(
                id=str(d["id"]),
                settings_levels=levels,
                default_settings=ScanSettings(**{k: float(d["default_settings"][k]) for k in SETTING_NAMES}),
                settings_range=rng,
                profile_rate_hz=float(d.get("profile_rate_hz", 2000.0)),
                effects=dict(d.get("effects") or {}),
                source=source,
                serial=str(d.get("serial", "") or ""),
                description=str(d.get("description", "") or ""),
                **geom,
            )
        except (KeyError, TypeError, IndexError) as e:
            raise ValueError(f"scanner config {where} is missing or malformed: {e!r}") from e
        model.default_settings.validate(model.settings_range)
        return model

    def with_levels(self, levels: dict[str, tuple[float, ...]]) -> ScannerModel:
        """The same scanner with the settings levels of a campaign."""
        from dataclasses import replace

        return replace(self, settings_levels={k: tuple(float(x) for x in levels[k]) for k in SETTING_NAMES})

    def study_configurations(self) -> list[ScanSettings]:
        """The 27 (3 x 3 x 3) configurations of the study, in a fixed order (lateral, direction, exposure).

        Raises:
            ValueError: the scanner description has no settings levels (give a campaign's, ``with_levels``).
        """
        lv = self.settings_levels
        if lv is None:
            raise ValueError(f"scanner {self.id!r} has no settings levels (a data sheet gives none): take them from "
                             "the calibration campaign")
        return [
            ScanSettings(a, b, c)
            for a, b, c in itertools.product(lv["lateral_density"], lv["direction_density"], lv["exposure_ms"])
        ]

    def validate_settings(self, s: ScanSettings) -> ScanSettings:
        """``s`` if within this scanner's valid ranges; SettingsError otherwise."""
        return s.validate(self.settings_range)


def _pair(v: Any, what: str, where: str) -> tuple[float, float]:
    a, b = float(v[0]), float(v[1])
    if not (math.isfinite(a) and math.isfinite(b) and 0 <= a < b):
        raise ValueError(f"scanner config {where}: {what} must be two increasing non-negative numbers, got {v!r}")
    return a, b


def _model_geometry(d: dict[str, Any], where: str) -> dict[str, Any]:
    """Geometry in the model's own terms (the original YAML)."""
    if "camera_mm" in d:
        cam = tuple(float(x) for x in d["camera_mm"])
        if len(cam) != 3:
            raise ValueError(f"scanner config {where}: camera_mm needs three numbers")
    else:
        cam = (0.0, float(d["baseline_mm"]), 0.0)
    return {"standoff_mm": float(d["standoff_mm"]), "camera_mm": cam, "fan_angle_deg": float(d["fan_angle_deg"]),
            "depth_of_field_mm": _pair(d["depth_of_field_mm"], "depth_of_field_mm", where)}


def _datasheet_geometry(d: dict[str, Any], where: str) -> dict[str, Any]:
    """Geometry from data-sheet terms (see :class:`ScannerModel`), in the model's terms (head frame at the source).

    The laser source is where the fan's edges meet: ``behind`` = its distance to the near end of the measuring
    range. The measuring range is counted from the sensor-frame origin along the laser axis, so that origin lies
    on the laser axis ``behind - near`` from the source (head frame: ``(0, 0, near - behind)``)."""
    near, far = _pair(d["measuring_range_mm"], "measuring_range_mm", where)
    fov_near, fov_far = (float(x) for x in d["field_of_view_mm"])
    if not (0 < fov_near < fov_far):
        raise ValueError(f"scanner config {where}: field_of_view_mm must grow with distance (near < far), "
                         f"got {d['field_of_view_mm']!r}")
    half_slope = 0.5 * (fov_far - fov_near) / (far - near)
    behind = 0.5 * fov_near / half_slope
    standoff = behind + 0.5 * (far - near)
    angle = math.radians(float(d["triangulation_angle_deg"]))
    if not 0 < angle < math.pi / 2:
        raise ValueError(f"scanner config {where}: triangulation_angle_deg must be in (0, 90)")
    side = str(d.get("camera_side", "+y")).lower()
    if side not in ("+y", "-y"):
        raise ValueError(f"scanner config {where}: camera_side must be +y or -y, got {side!r}")
    # camera_height_mm: how far the camera sits from the source along the laser direction (toward the part > 0).
    height = float(d.get("camera_height_mm", 0.0))
    cy = (standoff - height) * math.tan(angle) * (1.0 if side == "+y" else -1.0)
    axes = tuple(tuple(float(x) for x in ax)
                 for ax in (d.get("sensor_frame") or {}).get("axes", ((1, 0, 0), (0, 1, 0), (0, 0, 1))))
    if len(axes) != 3 or any(len(a) != 3 for a in axes):
        raise ValueError(f"scanner config {where}: sensor_frame.axes needs three axes of three numbers")
    return {"standoff_mm": standoff, "camera_mm": (0.0, cy, -height if height else 0.0),
            "fan_angle_deg": math.degrees(2 * math.atan(half_slope)),
            "depth_of_field_mm": (behind, behind + (far - near)), "sensor_origin_mm": (0.0, 0.0, near - behind),
            "sensor_axes": axes}
