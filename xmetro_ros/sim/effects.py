"""Registry of the virtual scanner's effects (applied in this order) and their configuration."""

from __future__ import annotations

from typing import Any

from .anisotropy import Anisotropy
from .centroid import CentroidBias
from .depth_of_field import DepthOfField
from .edge import EdgeEffect
from .effect import Effect, EffectConfigError, UnknownEffectError
from .exposure import Exposure
from .incidence import Incidence
from .motion_blur import MotionBlur
from .outliers import Outliers
from .speckle import Speckle
from .standoff import Standoff

__all__ = ["EFFECTS", "effects_table", "resolve_effects"]

# Order matters: exposure sets the signal / noise gains the noise laws use; outliers come last.
EFFECTS: dict[str, type[Effect]] = {
    cls.name: cls
    for cls in (
        DepthOfField,
        Exposure,
        Standoff,
        Incidence,
        CentroidBias,
        EdgeEffect,
        Anisotropy,
        MotionBlur,
        Speckle,
        Outliers,
    )
}


def _check_names(cfg: dict[str, Any], where: str) -> None:
    if not isinstance(cfg, dict):
        raise EffectConfigError(f"{where} must be a mapping name -> {{enabled, params...}}, got {type(cfg).__name__}")
    unknown = [k for k in cfg if k not in EFFECTS]
    if unknown:
        raise UnknownEffectError(f"unknown effect(s) {unknown} in {where} (known: {', '.join(EFFECTS)})")


def resolve_effects(base: dict[str, Any] | None, override: dict[str, Any] | None) -> list[Effect]:
    """Instantiate the enabled effects, in registry order.

    Args:
        base: the scanner YAML's ``effects:`` section ({name: {enabled: bool, param: value, ...}}); an effect
            missing from it is enabled with its default parameters.
        override: the ``effects=`` argument, same shape, merged over ``base`` per effect (a bare bool toggles).
    """
    base = base or {}
    override = override or {}
    _check_names(base, "scanner effects config")
    _check_names(override, "effects=")
    out = []
    for name, cls in EFFECTS.items():
        cfg: dict[str, Any] = {}
        for src in (base.get(name), override.get(name)):
            if src is None:
                continue
            if isinstance(src, bool):
                src = {"enabled": src}
            if not isinstance(src, dict):
                raise EffectConfigError(f"effect {name!r}: config must be a mapping or a bool, got {src!r}")
            cfg.update(src)
        enabled = cfg.pop("enabled", True)
        if not isinstance(enabled, bool):
            raise EffectConfigError(f"effect {name!r}: enabled must be true/false, got {enabled!r}")
        if enabled:
            out.append(cls(**cfg))
    return out


def effects_table() -> str:
    """Markdown table of every effect: law, source, default magnitude, what it drives (for docs/simulator.md)."""
    rows = ["| effect | law | drives (systematic part) | magnitude | source |", "|---|---|---|---|---|"]
    for name, cls in EFFECTS.items():
        rows.append(f"| `{name}` | {cls.law} | {cls.drives} | {cls.magnitude} | {cls.source} |")
    return "\n".join(rows)
