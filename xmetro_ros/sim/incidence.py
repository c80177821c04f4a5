"""Incidence angle: falling signal → growing depth noise, and no return below the detection threshold."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from .effect import Effect, SimContext


class Incidence(Effect):
    """Noise growing with incidence and viewing angles; no return at grazing incidence (``source`` below)."""

    name = "incidence"
    law = (
        "signal S = cos(inc) * SNR gain; no return where S < min_signal; depth noise (along the ray) "
        "sigma = sigma_mm * noise_gain * cos(inc)^-exponent * cos(view)^-view_exponent (white, Gaussian)"
    )
    source = (
        "Soudarissanane et al., ISPRS Laser Scanning 2009 (noise vs incidence through the reflected signal); "
        "exponent calibrated on real AT C5 profiles of a 40 mm sphere (docs/simulator.md)"
    )
    magnitude = (
        "6.2 um depth noise at normal incidence, x cos(inc)^-1.4: circle-fit residual 9.6 / 16.7 / 25.6 um in the "
        "<60 / 60-70 / 70-80 deg bins (with the other effects)"
    )
    drives = "noise only (Inc, ViewAng); point presence at grazing incidence"
    defaults: ClassVar[dict[str, float | None]] = {
        "sigma_mm": 0.0062, "exponent": 1.4, "view_exponent": 0.3, "min_signal": 0.12,
    }
    positive = ("sigma_mm",)
    nonnegative = ("exponent", "view_exponent", "min_signal")

    def sigma(self, cos_inc: np.ndarray, cos_view: np.ndarray | float = 1.0, gain: np.ndarray | float = 1.0):
        p = self.values()
        return p["sigma_mm"] * gain * cos_inc ** (-p["exponent"]) * np.asarray(cos_view) ** (-p["view_exponent"])

    def apply(self, ctx: SimContext, rng: np.random.Generator) -> None:
        ci = ctx.cos_inc
        weak = ci * ctx.snr_gain < self.p("min_signal")
        ctx.keep &= ~weak
        ctx.stats["dropped_weak_signal"] = int(weak.sum())
        sig = self.sigma(ci, ctx.cos_view, ctx.noise_gain)
        ctx.add_rand(self.name, ctx.along_ray(sig * rng.standard_normal(ctx.m)))
        ctx.add_noise_cov(sig, ctx.d)
