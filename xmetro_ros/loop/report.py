"""Write ``DIR/report.json`` (schema ``xmetro.loop.report/1``, see docs/closed-loop.md), ``DIR/report.md`` and the
plots of the normal residual (mm) against each traced variable, before and after its correction (eval set)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .run import LoopResult

__all__ = ["write_report"]


def _plot(p: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = np.asarray(p["x"])
    rng = np.random.default_rng(0)
    sel = rng.choice(len(x), min(3000, len(x)), replace=False)
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for key, col in (("before", "tab:red"), ("after", "tab:blue")):
        y = np.asarray(p[key]) * 1e3
        ax.scatter(x[sel], y[sel], s=2, alpha=0.3, color=col, label=f"{key} (points)")
        if p.get("unit") == "id":  # identities: one mean per identity
            centers, idx = np.unique(x, return_inverse=True)
            nb = len(centers)
        else:
            edges = np.unique(np.quantile(x, np.linspace(0, 1, 17)))
            idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)
            nb = len(edges) - 1
            centers = 0.5 * (edges[:-1] + edges[1:])
        idx = idx.reshape(-1)
        m = np.bincount(idx, weights=y, minlength=nb) / np.maximum(np.bincount(idx, minlength=nb), 1)
        ax.plot(centers, m, color=col, lw=2, marker="o" if p.get("unit") == "id" else None,
                ls="" if p.get("unit") == "id" else "-", label=f"{key} (mean)")
    ax.set_xlabel(f"{p['variable']} [{p.get('unit', '')}]")
    ax.set_ylabel("residual along normal [µm]")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _table(m: dict) -> str:
    rows = ["| axis | MAE µm | R² | p95 µm |", "|---|---|---|---|"]
    for ax, v in m.items():
        rows.append(f"| {ax} | {v['mae'] * 1e3:.2f} | {v['r2']:.3f} | {v['p95'] * 1e3:.2f} |")
    return "\n".join(rows)


def write_report(result: LoopResult, out_dir: str | Path) -> Path:
    """Write report.json, report.md and loop_iter<k>_<variable>.png into ``out_dir``; return report.json."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rep = result.report
    plots = []
    for p in result.plots:
        name = f"loop_iter{p['iteration']}_{p['variable']}.png"
        _plot(p, out / name)
        plots.append(name)
    rep["plots"] = plots
    (out / "report.json").write_text(json.dumps(rep, indent=1))
    lines = [f"# Closed loop report ({rep['source']})", "",
             f"{rep['n_points']} points in {rep['n_groups']} {rep['hold_by']}s; roles: "
             + ", ".join(f"{k} {len(v['groups'])} ({v['n_points']} pts)" for k, v in rep["roles"].items()), "",
             f"Model: {rep['model']['kind']} {rep['model']['family']} on {', '.join(rep['model']['features'])}", "",
             "## Ground truth (eval part)", "", "```", json.dumps(rep["ground_truth"]["eval"], indent=1), "```", "",
             "## Candidates (iteration 1)", "", "| rank | name | kind | score | p | p (Holm) | significant |",
             "|---|---|---|---|---|---|---|"]
    for i, c in enumerate(rep["candidates"], 1):
        flag = ("yes" if c["significant"] else "no") + (" (in model)" if c["in_model"] else "")
        lines.append(f"| {i} | {c['name']} | {c['kind']} | {c['score']:.4f} | {c['p_value']:.2g} | "
                     f"{c['p_holm']:.2g} | {flag} |")
    lines += ["", "## Iterations", ""]
    for it in rep["iterations"]:
        sel = it["selected"]
        lines.append(f"- iteration {it['iteration']}: " + (f"added **{sel['name']}** as {sel['correction']} "
                                                            f"(score {sel['score']:.3f})" if sel else
                                                            "no significant effect found"))
    lines += ["", "## Before (eval part)", "", _table(rep["before"]), "", "## After (eval part)", "",
              _table(rep["after"]), ""]
    lines += [f"![{p}]({p})" for p in plots]
    (out / "report.md").write_text("\n".join(lines) + "\n")
    return out / "report.json"
