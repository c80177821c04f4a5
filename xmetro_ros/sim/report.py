"""Per-effect breakdown of the simulated error (the SHAP ground truth) and the docs figure.

``python -m xmetro_ros.sim.report OUT_DIR`` writes ``sim_effects.png`` (one scan coloured by each effect's
contribution) and prints the per-effect, per-axis mean |error| table used in docs/simulator.md.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from ..scan.artifacts import Sphere
from ..scan.scanner import ScannerModel
from .effect import SimContext
from .scanner_sim import simulate_scan

__all__ = ["contribution_table", "error_contributions", "plot_contributions"]


def error_contributions(ctx: SimContext, systematic: bool = True) -> dict[str, np.ndarray]:
    """Each effect's share of the per-axis error (nominal − measured, mm) of the kept points, linearised: a
    displacement c moves the error by −(c·n) n (radial / normal projection). Returns name → (K, 3)."""
    src = ctx.contributions if systematic else ctx.noise_contributions
    n = ctx.n[ctx.keep]
    out = {}
    for name, c in src.items():
        c = np.broadcast_to(c, ctx.sys.shape)[ctx.keep]
        out[name] = -np.einsum("ij,ij->i", c, n)[:, None] * n
    return out


def contribution_table(diameters=(35.0, 55.0), seed: int = 0) -> dict[str, np.ndarray]:
    """Mean |systematic error| per axis (um) of each effect over the spheres x the 27 study configurations."""
    scanner = ScannerModel.load()
    acc: dict[str, list[np.ndarray]] = {}
    for dia in diameters:
        for s in scanner.study_configurations():
            scan = simulate_scan(Sphere(dia / 2), s, scanner=scanner, seed=seed, keep_context=True)
            for name, e in error_contributions(scan.meta["_context"]).items():
                acc.setdefault(name, []).append(np.abs(e))
    return {k: np.concatenate(v).mean(axis=0) * 1e3 for k, v in acc.items()}


def plot_contributions(path: str | Path, diameter: float = 45.0, seed: int = 0) -> Path:
    """PNG: a 45 mm sphere (default settings) seen from above, coloured by each effect's normal error (um): one panel
    per effect and part (systematic, random), then the random and systematic totals."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scanner = ScannerModel.load()
    scan = simulate_scan(Sphere(diameter / 2), scanner.default_settings, scanner=scanner, seed=seed,
                         keep_context=True)
    ctx: SimContext = scan.meta["_context"]
    p = ctx.p[ctx.keep]
    n = ctx.n[ctx.keep]
    # one panel per effect and part (systematic, random), then the totals
    panels = [(f"{k} (systematic)", -np.einsum("ij,ij->i", np.broadcast_to(v, ctx.sys.shape)[ctx.keep], n))
              for k, v in ctx.contributions.items()]
    panels += [(f"{k} (random)", -np.einsum("ij,ij->i", np.broadcast_to(v, ctx.rand.shape)[ctx.keep], n))
               for k, v in ctx.noise_contributions.items()]
    panels.append(("total random", -np.einsum("ij,ij->i", ctx.rand[ctx.keep], n)))
    panels.append(("total systematic", -np.einsum("ij,ij->i", ctx.sys[ctx.keep], n)))
    cols = 4
    rows = int(np.ceil(len(panels) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(2.6 * cols, 2.5 * rows), dpi=70)
    sub = np.random.default_rng(0).permutation(len(p))[:12000]
    for ax, (name, val) in zip(axes.ravel(), panels, strict=True):
        v = val[sub] * 1e3
        lim = max(np.percentile(np.abs(v), 99), 1e-3)
        sc = ax.scatter(p[sub, 0], p[sub, 1], c=v, s=0.4, cmap="coolwarm", vmin=-lim, vmax=lim, rasterized=True)
        ax.set_title(name, fontsize=8)
        ax.set_aspect("equal")
        ax.tick_params(labelsize=6)
        fig.colorbar(sc, ax=ax, shrink=0.8).ax.tick_params(labelsize=6)
    for ax in axes.ravel()[len(panels):]:
        ax.axis("off")
    fig.suptitle(f"normal error contribution (um, + = measured inside), sphere D={diameter:g} mm, "
                 f"{scanner.default_settings.label()}; x, y in mm", fontsize=8)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path


if __name__ == "__main__":  # pragma: no cover - docs helper
    out = Path(sys.argv[1] if len(sys.argv) > 1 else ".")
    print(plot_contributions(out / "sim_effects.png"))
    for name, v in contribution_table().items():
        print(f"| `{name}` | {v[0]:.2f} | {v[1]:.2f} | {v[2]:.2f} |")
