"""Speckle noise, spatially correlated along and across the laser line (FFT-free Gaussian filtering on the grid)."""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from scipy.ndimage import gaussian_filter, gaussian_filter1d

from .effect import Effect, SimContext


def correlated_field(shape: tuple[int, int], sigma_px: tuple[float, float], rng: np.random.Generator) -> np.ndarray:
    """Unit-variance Gaussian random field on a grid, Gaussian correlation with std ``sigma_px`` (rows, cols)."""
    white = rng.standard_normal(shape)
    if max(sigma_px) <= 0:
        return white
    f = gaussian_filter(white, sigma=sigma_px, mode="wrap")
    # Exact variance of filtered white noise: sum of squared kernel weights (impulse response).
    imp = np.zeros((int(8 * sigma_px[0]) + 1, int(8 * sigma_px[1]) + 1))
    imp[imp.shape[0] // 2, imp.shape[1] // 2] = 1.0
    k = gaussian_filter(imp, sigma=sigma_px, mode="constant")
    return f / np.sqrt(np.sum(k**2))


def correlated_field_std(shape: tuple[int, int], sigma_px: tuple[float, float]) -> float:
    """Exact std of :func:`correlated_field` on a grid of ``shape`` (1 unless the grid is shorter than the
    kernel: the wrap-around folds the kernel onto itself). The filter is separable, so the variance of the wrapped
    filter is the product over both axes of the sum of squares of the folded 1-D kernel."""
    if max(sigma_px) <= 0:
        return 1.0
    var = 1.0
    for n, s in zip(shape, sigma_px, strict=True):
        delta = np.zeros(max(int(n), 1))
        delta[0] = 1.0
        folded = gaussian_filter1d(delta, sigma=s, mode="wrap") if s > 0 else delta
        var *= float(np.sum(folded**2))
    imp = np.zeros((int(8 * sigma_px[0]) + 1, int(8 * sigma_px[1]) + 1))
    imp[imp.shape[0] // 2, imp.shape[1] // 2] = 1.0
    k = gaussian_filter(imp, sigma=sigma_px, mode="constant")
    return float(np.sqrt(var / np.sum(k**2)))


class Speckle(Effect):
    """Speckle: spatially correlated depth noise (``source`` below)."""

    name = "speckle"
    law = (
        "depth noise along the ray, Gaussian, correlated with Gaussian correlation lengths corr_u_mm along the line "
        "and corr_s_mm across profiles; sigma = sigma_mm / sqrt(1 + blur / averaging_mm) (the moving head averages "
        "speckle grains)"
    )
    source = (
        "Dorsch, Haeusler & Herrmann, Appl. Opt. 33(7) 1306, 1994 (speckle limit of triangulation); "
        "Roos-Hoefgeest et al., Sensors 2023"
    )
    magnitude = "5 um depth noise, 0.3 mm x 0.6 mm correlation"
    drives = "noise only"
    defaults: ClassVar[dict[str, float | None]] = {
        "sigma_mm": 0.005, "corr_u_mm": 0.3, "corr_s_mm": 0.6, "averaging_mm": 0.5,
    }
    nonnegative = ("sigma_mm", "corr_u_mm", "corr_s_mm")
    positive = ("averaging_mm",)

    def apply(self, ctx: SimContext, rng: np.random.Generator) -> None:
        s = ctx.settings
        sigma_px = (self.p("corr_s_mm") * s.direction_density, self.p("corr_u_mm") * s.lateral_density)
        field = correlated_field(ctx.grid_shape, sigma_px, rng).reshape(-1)[ctx.index]
        sigma = self.p("sigma_mm") / np.sqrt(1.0 + ctx.blur_mm / self.p("averaging_mm"))
        ctx.add_rand(self.name, ctx.along_ray(sigma * field))
        # The correlation leaves each point's marginal law N(0, sigma²) except where the grid is shorter than the
        # kernel (wrap-around): the exact field std covers that.
        ctx.add_noise_cov(sigma * correlated_field_std(ctx.grid_shape, sigma_px), ctx.d)
