"""Report artefacts of a training run: the study's Tables 1-3 (markdown), deviation maps and SHAP summary plots."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .families import DISPLAY

__all__ = ["deviation_map", "shap_beeswarm", "tables_markdown"]

AXIS_NAMES = ("X", "Y", "Z")


def _fmt(s: dict | None, digits: int = 5) -> str:
    if not s or s.get("mean") is None or not np.isfinite(s["mean"]):
        return "n/a"
    return f"{s['mean']:.{digits}f} ± {s['std']:.{digits}f}"


def tables_markdown(metrics: dict) -> str:
    """The study's Tables 1-3 (one per axis) for every split in ``metrics`` (see docs/learning.md for the schema)."""
    lines = [f"# Model performance (profile `{metrics['profile']}`, seed {metrics['seed']})", ""]
    for split_name, split in metrics["splits"].items():
        lines += [f"## Split: {split_name} — {split['description']}", ""]
        for a, ax in enumerate("xyz"):
            lines += [f"### Table {a + 1}: model performance for {AXIS_NAMES[a]}-axis errors ({split_name} split)", "",
                      "| Model | MAE (mm) | R² | MAE / oracle floor |", "|---|---|---|---|"]
            for fam, per_axis in split["models"].items():
                m = per_axis.get(ax)
                if m is None:
                    continue
                ratio = m.get("ratio_to_oracle")
                ratio_s = f"{ratio:.2f}" if ratio is not None and np.isfinite(ratio) else "n/a"
                lines.append(f"| {DISPLAY.get(fam, fam)} | {_fmt(m['mae'])} | {_fmt(m['r2'], 2)} | {ratio_s} |")
            o = split["oracle"].get(ax)
            lines.append(f"| *oracle floor* (simulator's expected error) | {_fmt(o['mae']) if o else 'n/a'} | "
                         f"{_fmt(o['r2'], 2) if o else 'n/a'} | 1.00 |")
            lines.append("")
    iv = metrics.get("intervals") or {}
    if iv.get("families"):
        lines += ["## Calibrated 95 % intervals (cloud split, held-out configurations)", "", iv["description"], "",
                  f"{iv['n_clouds']} clouds, {iv['n_points']} points.", "",
                  "| Model | " + " | ".join(f"{ax.upper()} coverage | {ax.upper()} mean width (µm)" for ax in "xyz")
                  + " |", "|---|" + "---|---|" * 3]
        for fam, per_axis in iv["families"].items():
            cells = [f"{100 * per_axis[ax]['coverage']:.1f} % | {1e3 * per_axis[ax]['mean_width_mm']:.1f}"
                     for ax in "xyz"]
            lines.append(f"| {DISPLAY.get(fam, fam)} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def deviation_map(coords: np.ndarray, actual: np.ndarray, predicted: np.ndarray, axis: int, path: Path,
                  title: str = "") -> Path:
    """Predicted vs actual deviation map for one axis (like the study's Figs. 3-5): 3D scatter, mm."""
    plt = _plt()
    fig = plt.figure(figsize=(9, 3.6), dpi=80)
    for i, (vals, name) in enumerate(((actual, "actual"), (predicted, "predicted"))):
        # One colour scale per panel: the actual error carries the noise, the prediction only the systematic part.
        lim = float(np.nanpercentile(np.abs(vals), 98)) or 1e-6
        ax = fig.add_subplot(1, 2, i + 1, projection="3d")
        sc = ax.scatter(coords[:, 0], coords[:, 1], coords[:, 2], c=vals, cmap="coolwarm", vmin=-lim, vmax=lim, s=3)
        ax.set_title(f"{AXIS_NAMES[axis]} deviation, {name}", fontsize=9)
        ax.tick_params(labelsize=6)
        fig.colorbar(sc, ax=ax, shrink=0.6, label="mm")
    if title:
        fig.suptitle(title, fontsize=9)
    fig.savefig(path)
    plt.close(fig)
    return path


def shap_beeswarm(shap_values: np.ndarray, X: np.ndarray, feature_names: list[str], path: Path, title: str) -> Path:
    """SHAP summary (beeswarm) plot of one axis (like the study's Figs. 6-8)."""
    import shap

    plt = _plt()
    shap.summary_plot(shap_values, X, feature_names=feature_names, show=False, plot_size=(6, 4.5), max_display=14)
    fig = plt.gcf()
    fig.suptitle(title, fontsize=9)
    fig.savefig(path, dpi=70, bbox_inches="tight")
    plt.close(fig)
    return path
