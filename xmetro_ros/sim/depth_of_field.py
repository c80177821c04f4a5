"""Depth of field: no return outside the scanner's usable stand-off range."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from .effect import Effect, EffectConfigError, SimContext


class DepthOfField(Effect):
    """No return outside the scanner's depth of field (``source`` below)."""

    name = "depth_of_field"
    law = "no return where the stand-off r (distance along the laser axis) is outside [near_mm, far_mm]"
    source = "scanner data sheets (measuring range); the study's fixed 90 mm stand-off"
    magnitude = "default range: the scanner model's depth_of_field_mm (55-125 mm for xm-ls90)"
    drives = "point presence only (no error)"
    defaults: ClassVar[dict[str, float | None]] = {"near_mm": None, "far_mm": None}
    positive = ("near_mm", "far_mm")

    def check(self) -> None:
        near, far = self.params["near_mm"], self.params["far_mm"]
        if near is not None and far is not None and near >= far:
            raise EffectConfigError(f"effect {self.name!r}: near_mm ({near}) must be < far_mm ({far})")

    def limits(self, ctx: SimContext) -> tuple[float, float]:
        near = self.params["near_mm"] if self.params["near_mm"] is not None else ctx.scanner.depth_of_field_mm[0]
        far = self.params["far_mm"] if self.params["far_mm"] is not None else ctx.scanner.depth_of_field_mm[1]
        return near, far

    def apply(self, ctx: SimContext, rng: np.random.Generator) -> None:
        near, far = self.limits(ctx)
        out = (ctx.standoff < near) | (ctx.standoff > far)
        ctx.keep &= ~out
        ctx.stats["dropped_depth_of_field"] = int(out.sum())
