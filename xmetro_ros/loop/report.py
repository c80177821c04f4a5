"""Write ``DIR/report.json`` (schema ``xmetro.loop.report/2``, see docs/closed-loop.md), ``DIR/report.md`` and the
plots of the normal residual (mm) against each traced variable, before and after its correction (eval set).
The markdown shows *predictive* findings (features a live node computes; live before / after) apart from
*diagnostic* ones (offsets and oscillations that need the scan's ground truth)."""

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
             "## Candidates (iteration 1)", "", "| rank | name | kind | score | p | p (Holm) | spectral (score @ peak "
             "freq, Holm p) | significant |", "|---|---|---|---|---|---|---|---|"]
    for i, c in enumerate(rep["candidates"], 1):
        flag = ("yes (" + ", ".join(c.get("significant_by", [])) + ")" if c["significant"] else "no") + (
            " (in model)" if c["in_model"] else "") + (" (barred: fitted positions)" if c.get("confounded") else "")
        sp = c.get("spectral")
        spec = (f"{sp['score']:.3f} @ {sp['peak_frequency']:.4g}, p {sp['p_holm']:.2g}" if sp else "–")
        lines.append(f"| {i} | {c['name']} | {c['kind']} | {c['score']:.4f} | {c['p_value']:.2g} | "
                     f"{c['p_holm']:.2g} | {spec} | {flag} |")
    lines += ["", "## Predictive findings (a live node can use them)", ""]
    pr = rep.get("predictive", {})
    if pr.get("added"):
        lines += ["| iteration | added | correction | held-out gain (µm², ± s.e.; size µm) | spectral (peak, "
                  "coherence) | eval MAE normal µm after |", "|---|---|---|---|---|---|"]
        for st in pr["steps"]:
            sp = st.get("spectral") or {}
            spec = (f"{sp['score']:.3f} ({sp['peak_frequency']:.4g} /unit, {sp['phase_coherence']:.2f})"
                    if sp else "–")
            g = st.get("trace_gain_um") or {}
            gain = (f"{g['mse_um2']:.2f} ± {g['se_um2'] if g.get('se_um2') is not None else float('nan'):.2f}; "
                    f"{g['size_um']:.2f}" if g else "–")
            per = st.get("periodic")
            corr = (f"periodic {per['frequency']:.3g} {per['frequency_unit']}, {per['amplitude_um']:.2f} µm"
                    if per else "feature")
            lines.append(f"| {st['iteration']} | {st['variable']} | {corr} | {gain} | {spec} | "
                         f"{st['after']['normal']['mae'] * 1e3:.2f} |")
    else:
        lines.append("No predictive effect found (nothing a feature of a new scan can correct).")
    lines += ["", "Live before / after (eval part, no ground truth used):", "", "| | MAE normal µm | R² normal | "
              "p95 normal µm |", "|---|---|---|---|"]
    for k in ("before", "after"):
        m = rep[k]["normal"]
        lines.append(f"| {k} | {m['mae'] * 1e3:.2f} | {m['r2']:.3f} | {m['p95'] * 1e3:.2f} |")
    dg = rep.get("diagnostic", {})
    lines += ["", "## Diagnostic findings (need the scan's ground truth: never a live improvement)", ""]
    if not dg.get("findings"):
        lines.append("No diagnostic effect found.")
    for f in dg.get("findings", []):
        if f["kind"] == "offset":
            o = f["offsets"]
            lines += [f"### {f['variable']}: {f['structure']}", "",
                      f"{o['n_identities']} identities; |offset| median {o['median_um']:.1f} µm, max "
                      f"{o['max_um']:.1f} µm; median bootstrap s.e. {o['median_se_um']:.1f} µm ({o['bootstrap']['n']} "
                      f"draws of {o['bootstrap']['unit']}); direction coherence {o['direction_coherence']:.2f}; "
                      f"trace gain {f.get('trace_gain', 0) * 100:.0f} %.", "", f"Fix: {f['fix']}.", "",
                      "| identity | offset x / y / z µm | s.e. x / y / z µm | weakest-direction eigenvalue |",
                      "|---|---|---|---|"]
            for r in o["per_identity"][:30]:
                lines.append(f"| {r['identity']} | {' / '.join(f'{v:.1f}' for v in r['offset_um'])} | "
                             f"{' / '.join(f'{v:.1f}' for v in r['se_um'])} | {r['weakest_direction_eig']:.3g} |")
            if o["n_identities"] > 30:
                lines.append(f"| … {o['n_identities'] - 30} more (report.json lists {o['per_identity_shown']}) | | | |")
            lines.append("")
        else:
            lines += [f"### {f['variable']}: {f['structure']}", "",
                      f"peak {f['peak_frequency']:.4g} {f['unit']} (period {f['period']:.4g}), amplitude "
                      f"{f['amplitude_um']:.1f} µm, phase coherence {f['phase_coherence']:.2f} (1: locked to the "
                      f"variable), spectral score {f['spectral_score']:.3f}, Holm p {f['p_holm']:.2g}; "
                      + ("not tried as a feature (phase not locked)." if f["trace_gain_as_feature"] is None else
                         f"as a feature it did not lower the trace error (gain "
                         f"{f['trace_gain_as_feature'] * 100:.1f} %)."),
                      "", f"Fix: {f['fix']}.", ""]
            for a in f.get("also_seen_over", []):
                lines.append(f"- also seen over {a['variable']} (peak {a['peak_frequency']:.4g} {a['unit']})")
    for b in dg.get("barred_by_fitted_positions", []):
        lines.append(f"- `{b['variable']}` significant (score {b['score']:.3f}) but not selectable: {b['reason']}")
    if dg.get("eval_with_offsets"):
        m = dg["eval_with_offsets"]["normal"]
        lines += ["", f"With the offsets fitted on the eval groups' own ground truth (cross-fit, diagnostic only): "
                      f"MAE normal {m['mae'] * 1e3:.2f} µm, R² {m['r2']:.3f}, p95 {m['p95'] * 1e3:.2f} µm."]
    lines += ["", "## Iterations", ""]
    for it in rep["iterations"]:
        sel = it["selected"]
        lines.append(f"- iteration {it['iteration']}: " + (f"added **{sel['name']}** as {sel['correction']} "
                                                            f"({sel['finding']}, score {sel['score']:.3f})" if sel else
                                                            "no significant effect found"))
    lines += ["", "## Before (eval part)", "", _table(rep["before"]), "", "## After, live (eval part)", "",
              _table(rep["after"]), ""]
    lines += [f"![{p}]({p})" for p in plots]
    (out / "report.md").write_text("\n".join(lines) + "\n")
    return out / "report.json"
