"""Motion blur: the head moves during the exposure (head speed x exposure time)."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from .effect import Effect, SimContext


class MotionBlur(Effect):
    """Motion blur: the head moves during the exposure (``source`` below)."""

    name = "motion_blur"
    law = (
        "blur b = head speed x exposure (speed = 1 / (direction_density * profile period), period = max(1/rate, "
        "exposure)); the stripe integrates the surface over [-b/2, b/2] along the scan: depth = mean of substeps "
        "sub-ray depths (curvature and slope bias); an uncompensated trigger latency shifts the point along the "
        "scan by -latency_fraction * b (stamp lag); no return where fewer than min_fraction of the sub-rays hit"
    )
    source = "motion blur of line scanners at speed (Roos-Hoefgeest et al., Sensors 2023; maker guidance: speed x T)"
    magnitude = "b = 0.04-0.33 mm over the study's levels; Y shift up to 10 um at 3 /mm and 2 ms"
    drives = "Y (direction_density x exposure_time, N_y); Z slightly through curvature"
    defaults: ClassVar[dict[str, float | None]] = {"substeps": 5, "min_fraction": 0.5, "latency_fraction": 0.03}
    positive = ("substeps",)
    nonnegative = ("min_fraction", "latency_fraction")

    def apply(self, ctx: SimContext, rng: np.random.Generator) -> None:
        b = ctx.blur_mm
        ey = ctx.head_y
        # The profile is stamped latency_fraction * b too late: the point lands behind (-Y) where it was lit.
        shift = -self.p("latency_fraction") * b
        ctx.add_sys(self.name, np.broadcast_to(shift * ey, (ctx.m, 3)).copy())
        k = max(int(self.p("substeps")), 1)
        if b <= 0 or k == 1 or ctx.m == 0:
            return
        offsets = (np.arange(k) + 0.5) / k * b - b / 2
        depths = np.stack([ctx.artifact.intersect(ctx.origin + o * ey, ctx.d) for o in offsets])
        hit = np.isfinite(depths)
        frac = hit.mean(axis=0)
        mean = np.nanmean(np.where(hit, depths, np.nan), axis=0) if hit.any() else ctx.depth
        mean = np.where(frac > 0, mean, ctx.depth)
        ctx.keep &= frac >= self.p("min_fraction")
        ctx.add_sys(self.name, ctx.along_ray(mean - ctx.depth))
