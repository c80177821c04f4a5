"""Self-contained HTML report of a demo run (``out/demo/report.html``): tables and PNG figures embedded in base64.

Sections: per-scan quality table; per-scan deviation maps (predicted |deviation| and, where the artifact is known,
the actual |error| = |nominal − measured|, top view in the scan frame, µm colour scale); the SHAP explanation of the
worst region (mean |SHAP| per feature and axis, from ``~/explain``); the settings recommendation for that region
(from ``~/recommend_settings``). Inputs are plain numbers (mm, µm as labelled), so the writer needs no ROS.
"""

from __future__ import annotations

import base64
import html
import io
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..judge.flags import verdict_name

__all__ = ["ReportScan", "deviation_map_png", "shap_bar_png", "write_report"]


@dataclass
class ReportScan:
    """One scan of the report.

    Attributes:
        label: what was scanned and how (artifact, settings).
        quality: summary dict (``OutputSet.summary_dict()``: verdict, counts, mean/p95 |error| mm, message).
        points_mm: (N, 3) processed points in the scan frame, mm (None when the scan was in ERROR).
        predicted_mm: (N, 3) predictions, mm (NaN where none), in the sign of ``actual_mm`` (``deviation_arrays``
            gives the model's target nominal − measured; the report shows norms only, the same in either sign).
        actual_mm: (N, 3) actual errors nominal − measured, mm, where the artifact is known; else None.
        systematic_mm: (N, 3) noise-free systematic error (simulated scans: the simulator's expected error, nominal
            − measured), mm.
        uncertainty_mm: (N, 3) U (95 %) per axis as published (``ux, uy, uz``), mm (NaN where none).
        settings: the settings the scan was judged with (``ScanQuality.settings``), as text ('' when unknown).
        region_mm: (x, y, radius) of the region explained and recommended for (the worst region), scan frame, mm;
            circled on this scan's maps. None on other scans.
    """

    index: int
    label: str
    quality: dict[str, Any]
    points_mm: np.ndarray | None = None
    predicted_mm: np.ndarray | None = None
    actual_mm: np.ndarray | None = None
    systematic_mm: np.ndarray | None = None
    uncertainty_mm: np.ndarray | None = None
    settings: str = ""
    extra: dict[str, Any] = field(default_factory=dict)
    region_mm: tuple[float, float, float] | None = None


_COLOURS = {"OK": "#2e7d32", "WARN": "#ef6c00", "RESCAN": "#c62828", "ERROR": "#6a1b9a"}


def _png(fig: Any) -> str:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80, bbox_inches="tight")
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def deviation_map_png(points_mm: np.ndarray, panels: list[tuple[str, np.ndarray]], vmax_um: float | None = None,
                      max_points: int = 15000, label: str = "|error| [µm]",
                      region_mm: tuple[float, float, float] | None = None) -> str:
    """Base64 PNG: one top-view (x, y) scatter per panel, coloured by the norm of the panel's (N, 3) mm values, µm;
    ``region_mm`` (x, y, radius, mm) circled in red on every panel (the worst region)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # Scatter plots of ~10^5 points are slow and no clearer: an evenly spaced subset is drawn.
    step = max(1, len(points_mm) // max_points)
    points_mm = points_mm[::step]
    norms = [np.linalg.norm(v[::step], axis=1) * 1e3 for _, v in panels]
    if vmax_um is None:
        finite = np.concatenate([n[np.isfinite(n)] for n in norms]) if norms else np.zeros(1)
        vmax_um = float(np.percentile(finite, 99)) if finite.size else 1.0
    fig, axes = plt.subplots(1, len(panels), figsize=(4.4 * len(panels), 3.8), squeeze=False, layout="constrained")
    for ax, (title, _), n in zip(axes[0], panels, norms, strict=True):
        ok = np.isfinite(n) & np.isfinite(points_mm).all(axis=1)
        sc = ax.scatter(points_mm[ok, 0], points_mm[ok, 1], c=n[ok], s=2, cmap="viridis", vmin=0.0,
                        vmax=max(vmax_um, 1e-6), rasterized=True)
        if region_mm is not None:
            from matplotlib.patches import Circle

            ax.add_patch(Circle(region_mm[:2], max(region_mm[2], 0.5), fill=False, edgecolor="red", linewidth=1.5))
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("x [mm]")
        ax.set_ylabel("y [mm]")
        ax.set_aspect("equal")
        fig.colorbar(sc, ax=ax, label=label)
    return _png(fig)


def shap_bar_png(feature_names: list[str], mean_abs_shap_um: np.ndarray, axis_names: list[str]) -> str:
    """Base64 PNG: horizontal bars of mean |SHAP| (µm) per feature, one colour per axis."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    F = len(feature_names)
    A = len(axis_names)
    fig, ax = plt.subplots(figsize=(6.0, 0.3 * F + 1.2))
    y = np.arange(F)
    h = 0.8 / max(A, 1)
    for a in range(A):
        ax.barh(y + a * h, mean_abs_shap_um[:, a], height=h, label=f"axis {axis_names[a]}")
    ax.set_yticks(y + h * (A - 1) / 2)
    ax.set_yticklabels(feature_names, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("mean |SHAP| [µm]")
    ax.legend(fontsize=8)
    return _png(fig)


def feature_glossary(names: list[str]) -> dict[str, str]:
    """Feature name → its definition from the feature registry (the study's equations), for readers of a report;
    a name the registry does not know (a model of other features) maps to ''."""
    from ..judge.features import REGISTRY

    out = {}
    for n in names:
        try:
            out[n] = REGISTRY.get(n).formula
        except KeyError:
            out[n] = ""
    return out


def _e(x: Any) -> str:
    return html.escape(str(x))


def _table(header: list[str], rows: list[list[Any]], raw_cols: frozenset[int] = frozenset()) -> str:
    th = "".join(f"<th>{_e(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{c if i in raw_cols else _e(c)}</td>" for i, c in enumerate(r)) + "</tr>"
                   for r in rows)
    return f"<table><thead><tr>{th}</tr></thead><tbody>{body}</tbody></table>"


def write_report(
    path: str | Path,
    scans: list[ReportScan],
    *,
    explain: dict[str, Any] | None = None,
    recommend: dict[str, Any] | None = None,
    summary_lines: list[str] | None = None,
    meta: dict[str, Any] | None = None,
    title: str = "xmetro demo: replay through a live xmetro_node",
    services_note: str = "not requested",
    tolerance_m: float | None = None,
    tolerance_note: str = "the node's <code>tolerance</code>",
) -> Path:
    """Write the HTML report and return its path. ``title``: the page's heading; ``services_note``: what the
    ~/explain and ~/recommend_settings sections say when they were not asked (e.g. a report of a recorded bag);
    ``tolerance_m``: the tolerance the decisions were made against (metres), stated beside them with
    ``tolerance_note`` (HTML: where the value comes from).

    ``explain``: {"scan", "region", "feature_names", "feature_units", "axis_names", "mean_abs_shap_um" (F, A),
    "base_values_um", "n_points", "message"} or {"error": text}. ``recommend``: {"rows": [[label, value], ...],
    "alternatives": [[...], ...], "alternatives_header": [...], "message"} or {"error": text}.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{_e(title)}</title><style>",
             "body{font-family:sans-serif;max-width:1100px;margin:1em auto;color:#222}",
             "table{border-collapse:collapse;font-size:12px;margin:0.5em 0}",
             "td,th{border:1px solid #bbb;padding:3px 6px;text-align:right}th{background:#eee}",
             "td:first-child,th:first-child{text-align:left}.v{color:#fff;font-weight:bold;padding:2px 5px}",
             "pre{background:#f6f6f6;padding:0.6em;font-size:12px;white-space:pre-wrap}</style></head><body>",
             f"<h1>{_e(title)}</h1>"]
    if meta:
        parts.append(_table(["item", "value"], [[k, v] for k, v in meta.items()]))
    if summary_lines:
        parts.append("<h2>Summary</h2><pre>" + _e("\n".join(summary_lines)) + "</pre>")

    parts.append("<h2>Per-scan quality</h2>")
    rows = []
    for s in scans:
        q = s.quality
        vname = verdict_name(q["verdict"])
        badge = f"<span class='v' style='background:{_COLOURS.get(vname, '#555')}'>{_e(vname)}</span>"
        flags = ", ".join(f"{k}:{v}" for k, v in q.get("flag_counts", {}).items() if v)
        rows.append([
            s.index, _e(s.label), _e(s.settings or "-"), badge, q["error_code"], q["points_received"],
            q["points_valid"], q["points_flagged"], f"{q['usable_fraction']:.3f}",
            " / ".join(f"{v * 1e3:.2f}" for v in q["mean_abs_error_mm"]),
            " / ".join(f"{v * 1e3:.2f}" for v in q["p95_abs_error_mm"]),
            " / ".join("-" if not np.isfinite(v) else f"{v * 1e3:.2f}" for v in q.get("p95_uncertainty_mm",
                                                                                         [np.nan] * 3)),
            _e(" / ".join(str(v) for v in q.get("decisions", {}).values()) or "-"),
            "yes" if q["settings_defaulted"] else "no", _e(flags), _e(q["message"]),
        ])
    parts.append(_table(["#", "scan", "settings (as judged)", "verdict", "error", "received", "valid",
                         "flagged (of valid)", "usable (of valid)",
                         "mean |e| x/y/z [µm]", "p95 |e| x/y/z [µm]", "p95 U x/y/z [µm]",
                         "conforming / non-conforming / undecided", "defaulted", "flag counts", "message"],
                        rows, raw_cols=frozenset({1, 2, 3, 12, 14, 15})))
    rules = sorted({str(s.quality.get("decision_rule", "")) for s in scans} - {""})
    parts.append("<p>U: the expanded (95 %) uncertainty of each point's predicted deviation, per axis, calibrated "
                 "per incidence and exposure (docs/uncertainty.md). Decisions per ISO 14253-1"
                 + (f" ({_e(', '.join(rules))} rule)" if rules else "")
                 + " against " + (f"the tolerance {tolerance_m * 1e6:.1f} µm ({tolerance_note})"
                                  if tolerance_m is not None else "the node's <code>tolerance</code>")
                 + ": conforming and non-conforming are proved with U, "
                 "undecided are neither. Valid: finite points inside the working volume; usable and flagged are "
                 "shares and counts of the valid points (the verdict's figures).</p>")

    parts.append("<h2>Deviation maps</h2><p>Top view (x, y) of each processed scan in its frame, coloured by the "
                 "norm of the predicted deviation (dx, dy, dz of ~/deviations) and, for "
                 "simulated scans whose artifact is known, the actual error of each point (noise included) and the "
                 "simulator's noise-free systematic error, on the same scale.</p>")
    for s in scans:
        if s.points_mm is None or s.predicted_mm is None:
            parts.append(f"<h3>#{s.index} {_e(s.label)}</h3><p>no deviations (scan in ERROR)</p>")
            continue
        panels = [("predicted |deviation|", s.predicted_mm)]
        if s.actual_mm is not None:
            panels.append(("actual |error| (known artifact)", s.actual_mm))
            d = s.actual_mm - s.predicted_mm
            ok = np.isfinite(d).all(axis=1)
            if ok.any():
                rmse = float(np.sqrt(np.mean(np.sum(d[ok] ** 2, axis=1)))) * 1e3
                s.extra.setdefault("rmse vs actual [µm]", f"{rmse:.2f}")
        if s.systematic_mm is not None:
            panels.append(("systematic |error| (simulator, noise-free)", s.systematic_mm))
            d = s.systematic_mm - s.predicted_mm
            ok = np.isfinite(d).all(axis=1)
            if ok.any():
                rmse = float(np.sqrt(np.mean(np.sum(d[ok] ** 2, axis=1)))) * 1e3
                s.extra.setdefault("rmse vs systematic [µm]", f"{rmse:.2f}")
        img = deviation_map_png(s.points_mm, panels, region_mm=s.region_mm)
        extra = "; ".join(f"{k}: {v}" for k, v in s.extra.items())
        if s.region_mm is not None:
            extra = "; ".join(filter(None, [extra, "red circle: the worst region, explained and recommended below"]))
        parts.append(f"<h3>#{s.index} {_e(s.label)}</h3><p>{_e(extra)}</p>"
                     f"<img alt='deviation map {s.index}' src='data:image/png;base64,{img}'/>")
        if s.uncertainty_mm is not None and np.isfinite(s.uncertainty_mm).any():
            # U on its own scale: it is wider than the deviations by construction (95 % of the error about d).
            uimg = deviation_map_png(s.points_mm, [("U, 95 % (norm of ux, uy, uz)", s.uncertainty_mm)],
                                     label="U [µm]", region_mm=s.region_mm)
            parts.append(f"<img alt='uncertainty map {s.index}' src='data:image/png;base64,{uimg}'/>")

    parts.append("<h2>Why is the worst region bad? (~/explain, SHAP)</h2>")
    if not explain:
        parts.append(f"<p>{_e(services_note)}</p>")
    elif "error" in explain:
        parts.append(f"<p><b>~/explain failed:</b> {_e(explain['error'])}</p>")
    else:
        ms = np.asarray(explain["mean_abs_shap_um"], dtype=float)
        parts.append(f"<p>{_e(explain.get('region', ''))} — {explain['n_points']} points explained; base values "
                     f"{_e(explain.get('base_values_um'))} µm. {_e(explain.get('message', ''))}</p>")
        parts.append(f"<img alt='shap' src='data:image/png;base64,"
                     f"{shap_bar_png(explain['feature_names'], ms, explain['axis_names'])}'/>")
        order = np.argsort(-ms.sum(axis=1))
        meaning = feature_glossary(explain["feature_names"])
        parts.append(_table(["feature", "what it is", "unit", *[f"mean |SHAP| {a} [µm]" for a in explain["axis_names"]],
                             "sum over axes [µm]"],
                            [[explain["feature_names"][i], _e(meaning.get(explain["feature_names"][i], "")),
                              explain["feature_units"][i], *[f"{v:.3f}" for v in ms[i]], f"{ms[i].sum():.3f}"]
                             for i in order], raw_cols=frozenset({1})))

    parts.append("<h2>How to rescan it? (~/recommend_settings)</h2>")
    if not recommend:
        parts.append(f"<p>{_e(services_note)}</p>")
    elif "error" in recommend:
        parts.append(f"<p><b>~/recommend_settings failed:</b> {_e(recommend['error'])}</p>")
    else:
        parts.append(f"<p>{_e(recommend.get('message', ''))}</p>")
        parts.append(_table(["", "value"], recommend["rows"]))
        if recommend.get("alternatives"):
            parts.append("<p>Best alternatives (ranked):</p>")
            parts.append(_table(recommend["alternatives_header"], recommend["alternatives"]))
    parts.append("</body></html>")
    path.write_text("\n".join(parts), encoding="utf-8")
    return path
