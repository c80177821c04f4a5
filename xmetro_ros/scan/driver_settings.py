"""Scan settings from a line-scanner driver's ROS parameters (ROS-free): a documented mapping per driver.

A driver node declares its own parameters (exposure in µs, a profile period, points per profile, ...). A
:class:`DriverSettingsMapping` (``config/drivers/<name>.yaml``) says which of them give which of our settings and
how to convert them; :func:`settings_from_parameters` applies it to the values read from the driver and returns a
:class:`DriverSettings`: the settings (mm, ms, per-mm densities, as :class:`~.scanner.ScanSettings`), the profile
rate, and for each setting where it came from (``driver``, ``measured`` or ``default``) with a sentence saying so.
The ROS side (reading the parameters at start, following ``/parameter_events``) is
:class:`xmetro_ros.ros.driver_params.DriverParameterFollower`.

A mapping entry (``settings.<setting>``), ours = f(the driver's value):

- ``parameter``: the driver's parameter name; ``types``: the ROS types accepted (``integer``, ``double``,
  ``string``, ``bool``; default integer and double); ``unit``: the driver's unit (documentation);
- ``table``: optional, the driver's value → a number in ``unit`` (a driver that gives a setting as an index or a
  name); ``unset``: driver values that mean "not known" (the setting is then defaulted);
- ``scale`` (ours = value · scale, default 1) or ``reciprocal`` (ours = reciprocal / value: a period → a rate);
- lateral density only: ``line_width_mm`` — a number (the sensor model's measuring-range width at its reference
  stand-off) or ``scanner_model`` (our scanner model's fan there, 2 · stand-off · tan(fan / 2)); the converted
  value is then points per profile and the lateral density = points per profile / line width.

Settings: ``exposure_ms``, ``lateral_density``, ``direction_density`` (:data:`~.scanner.SETTING_NAMES`) and
``profile_rate_hz`` (not a scan setting: the profile stream's rate, with which the direction density = rate / speed).
``absent.<setting>`` documents why a driver does not give a setting. For a profile stream the direction density is
set by the motion: the caller measures it from the posed profiles and passes it as ``measured``.

Precedence per setting: the driver's value (mapped, present, valid) → the measured one → the default. A bad value
(wrong type, not finite, not positive, outside the scanner's ``settings_range``) is a :class:`DriverMappingError`
(``strict=True``) or is reported in ``errors`` and the setting falls back (``strict=False``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from .resources import config_path
from .scanner import SETTING_NAMES, ScannerModel, ScanSettings, SettingsError

__all__ = [
    "ALL_SETTINGS",
    "DRIVERS_DIR",
    "DriverMappingError",
    "DriverSettings",
    "DriverSettingsMapping",
    "ParameterMapping",
    "list_mappings",
    "load_mapping",
    "scanner_line_width_mm",
    "settings_from_parameters",
]

#: Everything a mapping may give: the three scan settings and the profile rate.
ALL_SETTINGS: tuple[str, ...] = (*SETTING_NAMES, "profile_rate_hz")
#: Folder of the shipped mappings, inside config/.
DRIVERS_DIR = "drivers"
_UNITS = {"lateral_density": "points/mm", "direction_density": "profiles/mm", "exposure_ms": "ms",
          "profile_rate_hz": "Hz"}
_ROS_TYPES = {"integer": "an integer", "double": "a double", "string": "a string", "bool": "a bool"}
_ENTRY_KEYS = {"parameter", "types", "unit", "scale", "reciprocal", "table", "unset", "line_width_mm", "note"}
_TOP_KEYS = {"name", "driver", "source", "node", "note", "settings", "absent"}
SCANNER_MODEL = "scanner_model"


class DriverMappingError(ValueError):
    """A mapping file that is malformed, or a driver value that cannot give a setting (wrong type, not a finite
    positive number, not in the mapping's table, outside the scanner's range). ``setting`` and ``parameter`` name
    what it is about ('' for the mapping as a whole)."""

    def __init__(self, message: str, setting: str = "", parameter: str = "") -> None:
        super().__init__(message)
        self.setting = setting
        self.parameter = parameter


@dataclass(frozen=True)
class ParameterMapping:
    """How one driver parameter gives one of our settings (see the module docstring)."""

    setting: str
    parameter: str
    types: tuple[str, ...] = ("integer", "double")
    unit: str = ""
    scale: float = 1.0
    reciprocal: float | None = None
    table: Mapping[Any, float] | None = None
    unset: tuple[Any, ...] = ()
    line_width_mm: float | str | None = None
    note: str = ""

    def describe(self) -> str:
        """``parameter [unit]`` and the conversion, for messages and the docs."""
        unit = f" [{self.unit}]" if self.unit else ""
        if self.reciprocal is not None:
            conv = f"{self.reciprocal:g} / value"
        elif self.scale != 1.0:
            conv = f"value × {self.scale:g}"
        else:
            conv = "value"
        if self.table:
            conv = conv.replace("value", "table[value]")
        if self.line_width_mm is not None:
            width = "the scanner model's line width" if self.line_width_mm == SCANNER_MODEL \
                else f"{float(self.line_width_mm):g} mm"
            conv = f"({conv}) / {width}"
        return f"{self.parameter}{unit} → {self.setting} = {conv}"


@dataclass(frozen=True)
class DriverSettingsMapping:
    """A driver's parameters → our settings (``config/drivers/<name>.yaml``).

    Attributes:
        name: the mapping's name (its file name without ``.yaml``).
        driver: the driver, in words; source: repository@commit and file the parameter names were read from.
        node: the driver node's default fully qualified name (``/lls_driver``).
        settings: setting → :class:`ParameterMapping` (only those the driver gives).
        absent: setting → why the driver does not give it (documentation, and the defaulted message).
        note: what a user should know (e.g. when the driver applies a changed parameter).
    """

    name: str
    driver: str = ""
    source: str = ""
    node: str = ""
    settings: Mapping[str, ParameterMapping] = field(default_factory=dict)
    absent: Mapping[str, str] = field(default_factory=dict)
    note: str = ""

    def parameter_names(self) -> tuple[str, ...]:
        """The driver parameters to read, each once, in the order of :data:`ALL_SETTINGS`."""
        names: list[str] = []
        for s in ALL_SETTINGS:
            m = self.settings.get(s)
            if m is not None and m.parameter not in names:
                names.append(m.parameter)
        return tuple(names)

    def needs_scanner(self) -> bool:
        """True when a line width is taken from the scanner model."""
        return any(m.line_width_mm == SCANNER_MODEL for m in self.settings.values())

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], name: str = "", where: str = "") -> DriverSettingsMapping:
        """From the YAML's mapping; DriverMappingError naming what is wrong."""
        where = where or name or "<dict>"
        if not isinstance(d, Mapping):
            raise DriverMappingError(f"driver mapping {where}: expected a mapping at the top, got {type(d).__name__}")
        unknown = set(d) - _TOP_KEYS
        if unknown:
            raise DriverMappingError(f"driver mapping {where}: unknown keys {sorted(unknown)} (known: "
                                     f"{sorted(_TOP_KEYS)})")
        settings = d.get("settings") or {}
        absent = d.get("absent") or {}
        if not isinstance(settings, Mapping) or not isinstance(absent, Mapping):
            raise DriverMappingError(f"driver mapping {where}: 'settings' and 'absent' must be mappings")
        for key in (*settings, *absent):
            if key not in ALL_SETTINGS:
                raise DriverMappingError(f"driver mapping {where}: unknown setting {key!r} (one of: "
                                         f"{', '.join(ALL_SETTINGS)})", setting=str(key))
        both = set(settings) & set(absent)
        if both:
            raise DriverMappingError(f"driver mapping {where}: {sorted(both)} both mapped and absent")
        entries = {str(k): _entry(str(k), v, where) for k, v in settings.items()}
        return cls(name=str(d.get("name") or name), driver=str(d.get("driver") or ""),
                   source=str(d.get("source") or ""), node=_fqn(str(d.get("node") or "")) if d.get("node") else "",
                   settings=entries, absent={str(k): str(v) for k, v in absent.items()},
                   note=str(d.get("note") or ""))


def _entry(setting: str, v: Any, where: str) -> ParameterMapping:
    def bad(msg: str) -> DriverMappingError:
        return DriverMappingError(f"driver mapping {where}: settings.{setting}: {msg}", setting=setting)

    if not isinstance(v, Mapping):
        raise bad(f"expected a mapping with 'parameter', got {v!r}")
    unknown = set(v) - _ENTRY_KEYS
    if unknown:
        raise bad(f"unknown keys {sorted(unknown)} (known: {sorted(_ENTRY_KEYS)})")
    param = v.get("parameter")
    if not isinstance(param, str) or not param:
        raise bad("'parameter' (the driver's parameter name) is required")
    types = v.get("types", ["integer", "double"])
    types = [types] if isinstance(types, str) else list(types)
    if not types or any(t not in _ROS_TYPES for t in types):
        raise bad(f"types must be some of {sorted(_ROS_TYPES)}, got {types!r}")
    scale = _number(v.get("scale", 1.0), "scale", bad)
    reciprocal = None if v.get("reciprocal") is None else _number(v["reciprocal"], "reciprocal", bad)
    if reciprocal is not None and "scale" in v:
        raise bad("give either 'scale' or 'reciprocal', not both")
    table = None
    if v.get("table") is not None:
        if not isinstance(v["table"], Mapping) or not v["table"]:
            raise bad("'table' must be a non-empty mapping of driver value → number")
        table = {k: _number(x, f"table[{k!r}]", bad) for k, x in v["table"].items()}
    elif any(t in ("string", "bool") for t in types):
        raise bad("a string or bool parameter needs a 'table' (driver value → number)")
    unset = v.get("unset", [])
    unset = tuple(unset) if isinstance(unset, (list, tuple)) else (unset,)
    width = v.get("line_width_mm")
    if width is not None:
        if setting != "lateral_density":
            raise bad("'line_width_mm' is for lateral_density only")
        if width != SCANNER_MODEL:
            width = _number(width, "line_width_mm", bad)
    return ParameterMapping(setting=setting, parameter=param, types=tuple(types), unit=str(v.get("unit", "")),
                            scale=scale, reciprocal=reciprocal, table=table, unset=unset, line_width_mm=width,
                            note=str(v.get("note", "")))


def _number(x: Any, what: str, bad: Any) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) or x <= 0:
        raise bad(f"{what} must be a positive finite number, got {x!r}")
    return float(x)


def _fqn(name: str) -> str:
    return name if name.startswith("/") else "/" + name


def _drivers_dir() -> Path:
    return config_path(DRIVERS_DIR)


def list_mappings() -> list[str]:
    """Names of the shipped mappings (``config/drivers/*.yaml``), sorted."""
    try:
        folder = _drivers_dir()
    except FileNotFoundError:
        return []
    return sorted(p.stem for p in folder.glob("*.yaml"))


def load_mapping(name_or_path: str | Path) -> DriverSettingsMapping:
    """A shipped mapping by name (``scancontrol_lls``) or a mapping file by path.

    Raises:
        DriverMappingError: unknown name (the message lists the shipped ones), unreadable or malformed file.
    """
    s = str(name_or_path)
    looks_like_path = isinstance(name_or_path, Path) or "/" in s or s.endswith((".yaml", ".yml"))
    if looks_like_path:
        p = Path(s)
    else:
        try:
            p = _drivers_dir() / f"{s}.yaml"
        except FileNotFoundError as e:
            raise DriverMappingError(f"no driver mappings shipped here ({e})") from e
        if not p.is_file():
            raise DriverMappingError(f"no driver mapping named {s!r} (shipped: {', '.join(list_mappings()) or 'none'}"
                                     f"; or give a path to a YAML file)")
    try:
        data = yaml.safe_load(p.read_text())
    except OSError as e:
        raise DriverMappingError(f"driver mapping {p} cannot be read: {e}") from e
    except yaml.YAMLError as e:
        raise DriverMappingError(f"driver mapping {p} is not valid YAML: {e}") from e
    return DriverSettingsMapping.from_dict(data, name=p.stem, where=str(p))


def scanner_line_width_mm(scanner: ScannerModel) -> float:
    """Length of the laser line at the scanner's reference stand-off: 2 · stand-off · tan(fan / 2), mm."""
    return 2.0 * scanner.standoff_mm * math.tan(math.radians(scanner.fan_angle_deg) / 2.0)


@dataclass(frozen=True)
class DriverSettings:
    """Settings from a driver's parameters, with where each one came from.

    Attributes:
        settings: the scan settings (per mm, ms).
        profile_rate_hz: the profile rate (Hz), None when neither the driver nor the scanner model gives one.
        sources: per name of :data:`ALL_SETTINGS`: ``driver``, ``measured``, ``default`` or ``none``.
        messages: per name, a sentence: the value, its unit and where it came from (for a default: why).
        errors: bad driver or measured values that were set aside (``strict=False``), one sentence each.
        parameters: the driver's raw values used, by parameter name.
        mapping: the mapping's name; node: the driver node ('' when not known).
    """

    settings: ScanSettings
    profile_rate_hz: float | None
    sources: Mapping[str, str]
    messages: Mapping[str, str]
    errors: tuple[str, ...] = ()
    parameters: Mapping[str, Any] = field(default_factory=dict)
    mapping: str = ""
    node: str = ""

    def _with(self, source: str) -> tuple[str, ...]:
        return tuple(n for n in ALL_SETTINGS if self.sources.get(n) == source)

    @property
    def from_driver(self) -> tuple[str, ...]:
        """Names whose value came from the driver's parameters."""
        return self._with("driver")

    @property
    def measured(self) -> tuple[str, ...]:
        """Names whose value was measured (e.g. the direction density from the posed profiles)."""
        return self._with("measured")

    @property
    def defaulted(self) -> tuple[str, ...]:
        """Scan settings (of :data:`SETTING_NAMES`) that took the default (the profile rate is not a scan setting)."""
        return tuple(n for n in SETTING_NAMES if self.sources.get(n) == "default")

    @property
    def settings_defaulted(self) -> bool:
        """True when any scan setting took the default."""
        return bool(self.defaulted)

    def defaulted_message(self) -> str:
        """One line naming each defaulted setting and why ('' when none)."""
        return "; ".join(self.messages[n] for n in self.defaulted)

    def summary(self) -> str:
        """One line: every setting, its value and its source."""
        return "; ".join(self.messages[n] for n in ALL_SETTINGS if n in self.messages)

    def diagnostic_values(self) -> dict[str, str]:
        """Key/value pairs for /diagnostics: ``settings_defaulted`` (the names, or ``none``), each setting's value
        and source, the errors."""
        out = {"settings_defaulted": ", ".join(self.defaulted) or "none"}
        values = dict(zip(SETTING_NAMES, self.settings.as_tuple(), strict=True))
        for n in ALL_SETTINGS:
            v = values.get(n, self.profile_rate_hz)
            out[n] = "n/a" if v is None else f"{v:g} {_UNITS[n]}"
            out[f"{n}_source"] = self.sources.get(n, "none")
        out["settings_errors"] = " | ".join(self.errors) or "none"
        return out


def _type_name(v: Any) -> str:
    if isinstance(v, bool):
        return "bool"
    if isinstance(v, int):
        return "integer"
    if isinstance(v, float):
        return "double"
    if isinstance(v, str):
        return "string"
    if isinstance(v, (list, tuple, bytes, bytearray)):
        return "array"
    return type(v).__name__


def _fmt(v: Any) -> str:
    return repr(v) if isinstance(v, str) else f"{v}"


def _convert(m: ParameterMapping, raw: Any, width_mm: float | None, where: str) -> float:
    """The driver's raw value → ours (DriverMappingError when it cannot be)."""
    def bad(msg: str) -> DriverMappingError:
        return DriverMappingError(f"{where}: parameter {m.parameter} {msg}", setting=m.setting, parameter=m.parameter)

    kind = _type_name(raw)
    if kind not in m.types:
        want = " or ".join(_ROS_TYPES[t] for t in m.types)
        raise bad(f"must be {want}{f' ({m.unit})' if m.unit else ''}, got {kind} {_fmt(raw)}")
    if m.table is not None:
        if raw not in m.table:
            raise bad(f"= {_fmt(raw)} is not in the mapping's table ({', '.join(map(_fmt, m.table))})")
        x = float(m.table[raw])
    else:
        x = float(raw)
    if not math.isfinite(x) or x <= 0:
        raise bad(f"= {_fmt(raw)}: must be a positive finite number")
    y = m.reciprocal / x if m.reciprocal is not None else x * m.scale
    if m.line_width_mm is not None:
        if width_mm is None:
            raise bad("needs the line width (the scanner model's)")
        y /= width_mm
    return y


def _check_range(name: str, value: float, ranges: Mapping[str, tuple[float, float]] | None) -> None:
    """SettingsError when ``value`` is not a positive finite number or is outside ``ranges[name]`` (the scanner's
    validation, :meth:`ScanSettings.validate`)."""
    if name not in SETTING_NAMES:
        if not math.isfinite(value) or value <= 0:
            raise SettingsError(f"{name} must be a positive finite number, got {value!r}")
        return
    probe = {n: (value if n == name else 1.0) for n in SETTING_NAMES}
    ScanSettings(**probe).validate({name: ranges[name]} if ranges and name in ranges else None)


def _resolve_defaults(defaults: Any, scanner: ScannerModel | None) -> tuple[dict[str, float], ScannerModel | None]:
    if isinstance(defaults, ScannerModel):
        scanner = scanner or defaults
        defaults = defaults.default_settings
    try:
        vals = {n: float(getattr(defaults, n)) for n in SETTING_NAMES}
    except (AttributeError, TypeError, ValueError) as e:
        raise TypeError(f"defaults must be a ScanSettings or a ScannerModel (or have {', '.join(SETTING_NAMES)}), "
                        f"got {defaults!r}") from e
    return vals, scanner


def settings_from_parameters(mapping: DriverSettingsMapping, params: Mapping[str, Any], defaults: Any,
                             measured: Mapping[str, float] | None = None, *, scanner: ScannerModel | None = None,
                             ranges: Mapping[str, tuple[float, float]] | None = None, strict: bool = True,
                             unavailable: str = "", node: str = "") -> DriverSettings:
    """Our settings from the driver's parameter values.

    Args:
        mapping: the driver's mapping (:func:`load_mapping`).
        params: the driver's parameter values by name, as rclpy gives them (int, float, str, bool); a missing name
            or None = the driver has no such parameter (not declared, or not read yet).
        defaults: a :class:`~.scanner.ScanSettings` (or anything with its three attributes) or a
            :class:`~.scanner.ScannerModel` (its ``default_settings``; it is then also the ``scanner``).
        measured: values measured by the caller (ours: per mm, ms, Hz), e.g. ``{"direction_density": 4.2}``.
        scanner: the scanner model: its ``settings_range`` (unless ``ranges`` is given), its line width (for a
            mapping with ``line_width_mm: scanner_model``) and its ``profile_rate_hz`` as the rate's default.
        ranges: the valid range of each scan setting (default: the scanner's).
        strict: raise on a bad value; else report it in ``errors`` and fall back to the measured value or default.
        unavailable: why the driver's parameters could not be read at all ('' = they were), for the messages.
        node: the driver node's name, for the messages (default: the mapping's).

    Raises:
        DriverMappingError: (strict) a driver value of the wrong type, not a finite positive number, not in the
            table, or outside the range; a measured value likewise; a mapping that needs the scanner model without
            one.
    """
    dflt, scanner = _resolve_defaults(defaults, scanner)
    if ranges is None and scanner is not None:
        ranges = scanner.settings_range
    node = node or mapping.node
    who = f"{mapping.name} ({node})" if node else mapping.name
    width: float | None = None
    if mapping.needs_scanner():
        if scanner is None:
            raise DriverMappingError(f"{who}: the mapping takes the line width from the scanner model "
                                     "(line_width_mm: scanner_model) but no scanner model was given")
        width = scanner_line_width_mm(scanner)
    values: dict[str, float] = {}
    sources: dict[str, str] = {}
    messages: dict[str, str] = {}
    errors: list[str] = []
    used: dict[str, Any] = {}
    measured = dict(measured or {})
    for k in measured:
        if k not in ALL_SETTINGS:
            raise DriverMappingError(f"measured: unknown setting {k!r} (one of: {', '.join(ALL_SETTINGS)})",
                                     setting=k)

    def fail(err: DriverMappingError) -> None:
        if strict:
            raise err
        errors.append(str(err))

    for name in ALL_SETTINGS:
        unit = _UNITS[name]
        why_not = ""
        m = mapping.settings.get(name)
        if m is not None:
            raw = params.get(m.parameter)
            w = m.line_width_mm if isinstance(m.line_width_mm, float) else width
            if raw is None:
                why_not = (f"{unavailable}" if unavailable else
                           f"the driver has no parameter {m.parameter} (not declared)")
            elif not isinstance(raw, bool) and raw in m.unset:
                why_not = f"the driver's {m.parameter} = {_fmt(raw)} means not known yet"
            else:
                try:
                    v = _convert(m, raw, w, who)
                    try:
                        _check_range(name, v, ranges)
                    except SettingsError as e:
                        raise DriverMappingError(f"{who}: {e} (from {m.parameter} = {_fmt(raw)}"
                                                 f"{f' {m.unit}' if m.unit else ''})", setting=name,
                                                 parameter=m.parameter) from e
                except DriverMappingError as e:
                    fail(e)
                    reason = str(e).removeprefix(who + ": ")
                    why_not = f"the driver's {m.parameter} = {_fmt(raw)} was set aside: {reason}"
                else:
                    used[m.parameter] = raw
                    values[name], sources[name] = v, "driver"
                    width_txt = f", line {w:g} mm" if m.line_width_mm is not None and w is not None else ""
                    messages[name] = (f"{name} = {v:g} {unit} from the driver's {m.parameter} = {_fmt(raw)}"
                                      f"{f' {m.unit}' if m.unit else ''}{width_txt}")
                    continue
        else:
            why_not = f"{mapping.name} gives no {name}" + (f": {mapping.absent[name]}" if name in mapping.absent
                                                             else " (not mapped)")
        if name in measured:
            mv = measured[name]
            try:
                if isinstance(mv, bool) or not isinstance(mv, (int, float)):
                    raise SettingsError(f"{name} must be a positive finite number, got {mv!r}")
                _check_range(name, float(mv), ranges)
            except SettingsError as e:
                fail(DriverMappingError(f"measured {e}", setting=name))
            else:
                values[name], sources[name] = float(mv), "measured"
                messages[name] = f"{name} = {float(mv):g} {unit} measured ({why_not})"
                continue
        if name in SETTING_NAMES:
            values[name], sources[name] = dflt[name], "default"
            messages[name] = f"{name} = {dflt[name]:g} {unit} (default: {why_not})"
        elif scanner is not None:
            values[name], sources[name] = scanner.profile_rate_hz, "default"
            messages[name] = (f"{name} = {scanner.profile_rate_hz:g} {unit} (the scanner model's: {why_not})")
        else:
            sources[name] = "none"
            messages[name] = f"{name} not known ({why_not})"
    rate = values.get("profile_rate_hz")
    settings = ScanSettings(*(values[n] for n in SETTING_NAMES))
    return DriverSettings(settings=settings, profile_rate_hz=rate, sources=sources, messages=messages,
                          errors=tuple(errors), parameters=used, mapping=mapping.name, node=node)
