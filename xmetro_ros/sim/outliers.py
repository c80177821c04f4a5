"""Spurious returns (multiple reflections, ambient light): gross depth outliers for the outlier filter."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from .effect import Effect, EffectConfigError, SimContext


class Outliers(Effect):
    """Spurious returns off the surface, more at grazing incidence (``source`` below)."""

    name = "outliers"
    law = (
        "each point becomes a spurious return with probability fraction * (1 + grazing_boost * (1 - cos(inc))); "
        "it moves along the ray by +-U(min_mm, max_mm)"
    )
    source = "multiple reflections / secondary peaks on shiny curved parts (Roos-Hoefgeest et al., Sensors 2023)"
    magnitude = "~0.3-1 % of points, 0.2-1.5 mm off the surface"
    drives = "noise only (not in expected_error)"
    defaults: ClassVar[dict[str, float | None]] = {
        "fraction": 0.003, "grazing_boost": 2.0, "min_mm": 0.2, "max_mm": 1.5,
    }
    nonnegative = ("fraction", "grazing_boost", "min_mm")
    positive = ("max_mm",)

    def check(self) -> None:
        if self.p("fraction") > 1:
            raise EffectConfigError(f"effect {self.name!r}: fraction must be <= 1")
        if self.p("min_mm") > self.p("max_mm"):
            raise EffectConfigError(f"effect {self.name!r}: min_mm must be <= max_mm")

    def apply(self, ctx: SimContext, rng: np.random.Generator) -> None:
        p = self.values()
        prob = np.clip(p["fraction"] * (1.0 + p["grazing_boost"] * (1.0 - ctx.cos_inc)), 0.0, 1.0)
        hit = rng.random(ctx.m) < prob
        mag = rng.uniform(p["min_mm"], p["max_mm"], ctx.m) * rng.choice([-1.0, 1.0], ctx.m)
        ctx.add_rand(self.name, ctx.along_ray(np.where(hit, mag, 0.0)))
        ctx.stats["outliers"] = int((hit & ctx.keep).sum())
        ctx.stats["outlier_index"] = ctx.index[hit & ctx.keep]
