"""Lateral (along-the-line) errors: tilt-induced peak bias, distortion residual and sampling quantisation; none
along the scan axis."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from .effect import Effect, SimContext


class Anisotropy(Effect):
    """Anisotropic response: lateral bias on tilted surfaces and residual lens distortion (``source`` below)."""

    name = "anisotropy"
    law = (
        "lateral displacement in the laser plane (perpendicular to the ray, toward head +X): "
        "(a) peak bias on surfaces tilted along the line, tilt_mm * sin(gamma), sin(gamma) = N . lateral "
        "(the spot's footprint stretches along the line, its peak moves toward the near side); "
        "(b) distortion residual distortion_mm * (u / u_norm_mm)^3, u = ray position on the reference plane; "
        "(c) random quantisation sigma = quantization / lateral_density / sqrt(12). Nothing along "
        "the scan axis (encoder-accurate), so the scan axis Y is better than the lateral X, as the study states"
    )
    source = (
        "the study (sect. 1: anisotropic response, best along the axis of movement); lateral peak bias on tilted "
        "surfaces (Xu et al. 2009, along-line analogue); residual lens distortion (Isheil et al., Measurement 2011)"
    )
    magnitude = "X bias 10 um at sin(gamma) = 0.5, 20 um at the horizon; distortion 5 um at u = 22 mm; noise 2-5 um"
    drives = "X (N_x, ori_x, position u along the line; lateral_density through the noise)"
    defaults: ClassVar[dict[str, float | None]] = {
        "tilt_mm": 0.02, "distortion_mm": 0.008, "u_norm_mm": 25.0, "quantization": 0.1,
    }
    nonnegative = ("quantization",)
    positive = ("u_norm_mm",)

    @staticmethod
    def sin_gamma(ctx: SimContext) -> np.ndarray:
        """Sine of the surface tilt along the line, in the laser plane: N · lateral (the normal's share along it)."""
        return np.einsum("ij,ij->i", ctx.n, ctx.lateral_dir())

    def tilt_bias(self, sin_gamma: np.ndarray) -> np.ndarray:
        return self.p("tilt_mm") * sin_gamma

    def apply(self, ctx: SimContext, rng: np.random.Generator) -> None:
        p = self.values()
        lat = ctx.lateral_dir()
        sys = self.tilt_bias(self.sin_gamma(ctx)) + p["distortion_mm"] * (ctx.u_ref / p["u_norm_mm"]) ** 3
        ctx.add_sys(self.name, sys[:, None] * lat)
        sigma = p["quantization"] / ctx.settings.lateral_density / np.sqrt(12.0)
        ctx.add_rand(self.name, (sigma * rng.standard_normal(ctx.m))[:, None] * lat)
        ctx.add_noise_cov(sigma, lat)
