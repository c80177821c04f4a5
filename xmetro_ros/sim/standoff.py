"""Stand-off distance: residual depth bias of the triangulation calibration and defocus noise."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from .effect import Effect, SimContext


class Standoff(Effect):
    """Range error growing away from the reference stand-off (``source`` below)."""

    name = "standoff"
    law = (
        "zeta = (r - r_ref) / (half depth of field); depth bias = linear_mm * zeta + quadratic_mm * zeta^2 "
        "(positive = farther); SNR-limited noise x (1 + defocus_noise * zeta^2)"
    )
    source = (
        "range-dependent residual of triangulation calibration and defocus (Isheil et al., Measurement 44, 2011; "
        "Vukasinovic et al., Int. J. Adv. Manuf. Technol. 2010: error grows away from the reference distance)"
    )
    magnitude = "about -10 um at the top of a 55 mm sphere (r = 62.5 mm), 0 at r_ref = 90 mm"
    drives = "Z (feature R_y, i.e. stand-off / height); no effect on the lateral axes except through N_x, N_y"
    defaults: ClassVar[dict[str, float | None]] = {"linear_mm": 0.02, "quadratic_mm": 0.01, "defocus_noise": 0.5}
    nonnegative = ("defocus_noise",)

    def zeta(self, ctx: SimContext) -> np.ndarray:
        near, far = ctx.scanner.depth_of_field_mm
        return (ctx.standoff - ctx.scanner.standoff_mm) / (0.5 * (far - near))

    def bias(self, zeta: np.ndarray) -> np.ndarray:
        return self.p("linear_mm") * zeta + self.p("quadratic_mm") * zeta**2

    def apply(self, ctx: SimContext, rng: np.random.Generator) -> None:
        z = self.zeta(ctx)
        ctx.add_sys(self.name, ctx.along_ray(self.bias(z)))
        ctx.noise_gain *= 1.0 + self.p("defocus_noise") * z**2
