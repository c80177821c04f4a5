"""Edge effect at a curved artifact's horizon (grazing laser incidence)."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from .effect import Effect, SimContext


class EdgeEffect(Effect):
    """Range bias near the silhouette of the artifact (``source`` below)."""

    name = "edge"
    law = (
        "near the horizon seen from the laser the spot falls partly off the surface and the centroid moves toward "
        "the lit part: the point is pushed outward in the laser plane (perpendicular to the ray, along the normal's "
        "in-plane part w) by max_mm * exp(-(90 deg - inc) / width_deg) * |w|"
    )
    source = "edge effect of spheres scanned by line scanners: Sensors 24(8) 2410, 2024"
    magnitude = "~1.4 um at 70 deg incidence, ~7.5 um at 80 deg, up to max_mm = 40 um at the horizon"
    drives = "X on a sphere (points at the laser-line ends, large |N_x|, Inc near 0); outward (negative error)"
    defaults: ClassVar[dict[str, float | None]] = {"max_mm": 0.04, "width_deg": 6.0}
    nonnegative = ("max_mm",)
    positive = ("width_deg",)

    def magnitude_mm(self, inc_deg: np.ndarray) -> np.ndarray:
        return self.p("max_mm") * np.exp(-(90.0 - inc_deg) / self.p("width_deg"))

    def apply(self, ctx: SimContext, rng: np.random.Generator) -> None:
        inc = np.degrees(np.arccos(ctx.cos_inc))
        ey = ctx.head_y
        n = ctx.n
        # Normal's part in the laser plane, perpendicular to the ray.
        w = n - (np.einsum("ij,ij->i", n, ctx.d))[:, None] * ctx.d - np.outer(n @ ey, ey)
        ctx.add_sys(self.name, self.magnitude_mm(inc)[:, None] * w)
