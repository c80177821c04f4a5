"""The study's simulated campaign: 3 spheres x 27 configurations (+ cylinder, + optional plane), seeded per item."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..artifacts import Artifact, Cylinder, Plane, Sphere
from ..scan import Scan
from ..scanner import ScannerModel, ScanSettings
from .effects import resolve_effects
from .scanner_sim import DEFAULT_EXTENT_MM, simulate_scan

__all__ = ["CYLINDER_RADIUS_MM", "CampaignItem", "campaign_manifest", "item_seed", "study_campaign"]

CYLINDER_RADIUS_MM = 20.0


def item_seed(campaign_seed: int, index: int) -> int:
    """Seed of campaign item ``index``: derived from the campaign seed and the index (independent streams)."""
    return int(np.random.SeedSequence([int(campaign_seed), int(index)]).generate_state(1)[0])


@dataclass
class CampaignItem:
    """One scan of the campaign, simulated on demand with ``simulate()``."""

    index: int
    artifact: Artifact
    settings: ScanSettings
    config_index: int
    seed: int
    scanner: ScannerModel
    effects: dict[str, Any] | None = None
    extent_mm: float = DEFAULT_EXTENT_MM
    stamp_ns: int = 0
    tags: dict[str, Any] = field(default_factory=dict)

    def simulate(self) -> Scan:
        scan = simulate_scan(
            self.artifact,
            self.settings,
            scanner=self.scanner,
            effects=self.effects,
            seed=self.seed,
            stamp_ns=self.stamp_ns,
            extent_mm=self.extent_mm,
        )
        scan.meta.update({"item": self.index, "config_index": self.config_index, **self.tags})
        return scan

    def describe(self) -> dict[str, Any]:
        return {
            "index": self.index,
            "artifact": self.artifact.to_dict(),
            "config_index": self.config_index,
            "settings": {
                "lateral_density": self.settings.lateral_density,
                "direction_density": self.settings.direction_density,
                "exposure_ms": self.settings.exposure_ms,
            },
            "seed": self.seed,
            "stamp_ns": self.stamp_ns,
        }


def study_campaign(
    scanner: ScannerModel | None = None,
    seed: int = 0,
    sphere_diameters: tuple[float, ...] = (35.0, 45.0, 55.0),
    cylinder: bool = True,
    plane: bool = False,
    effects: dict[str, Any] | None = None,
    configurations: list[ScanSettings] | None = None,
    artifacts: list[Artifact] | None = None,
) -> list[CampaignItem]:
    """Items of the study campaign: each artifact (spheres of ``sphere_diameters`` mm centred at the origin, then
    a cylinder of radius 20 mm with its axis along Y, then optionally the z = 0 plane) x each configuration
    (default: the scanner's 27 study configurations). ``artifacts`` replaces that list when given.

    Raises ValueError for a non-positive diameter, UnknownEffectError / EffectConfigError for bad effects (checked
    up front, not at the first simulate())."""
    scanner = scanner if scanner is not None else ScannerModel.load()
    resolve_effects(scanner.effects, effects)  # fail fast on bad effect config
    if artifacts is None:
        artifacts = []
        for dia in sphere_diameters:
            if not (isinstance(dia, (int, float)) and np.isfinite(dia) and dia > 0):
                raise ValueError(f"sphere diameters must be positive numbers (mm), got {dia!r}")
            artifacts.append(Sphere(float(dia) / 2.0))
        if cylinder:
            artifacts.append(Cylinder(CYLINDER_RADIUS_MM))
        if plane:
            artifacts.append(Plane())
    configs = configurations if configurations is not None else scanner.study_configurations()
    for c in configs:
        scanner.validate_settings(c)
    items = []
    for a in artifacts:
        for ci, s in enumerate(configs):
            k = len(items)
            items.append(
                CampaignItem(
                    index=k,
                    artifact=a,
                    settings=s,
                    config_index=ci,
                    seed=item_seed(seed, k),
                    scanner=scanner,
                    effects=effects,
                    stamp_ns=1_700_000_000_000_000_000 + k * 1_000_000_000,
                )
            )
    return items


def campaign_manifest(
    items: list[CampaignItem], *, seed: int, effects: dict[str, Any] | None = None, extra: dict[str, Any] | None = None
) -> dict[str, Any]:
    """JSON-serialisable description of a campaign: seed, scanner, effects (enabled, with parameters), items.
    Holds no paths."""
    scanner = items[0].scanner if items else ScannerModel.load()
    fx = resolve_effects(scanner.effects, effects)
    from . import EFFECTS  # local: avoid an import cycle at module load

    return {
        "generator": "xmetro_ros.sim.campaign",
        "seed": int(seed),
        "scanner": scanner.id,
        "scanner_source": scanner.source,
        "effects": {e.name: dict(e.params) for e in fx},
        "effects_disabled": [n for n in EFFECTS if n not in {e.name for e in fx}],
        "n_items": len(items),
        "items": [it.describe() for it in items],
        **(extra or {}),
    }
