"""The campaign report of ``xmetro calibrate``: ``report.md``, a self-contained ``report.html`` (tables and PNG
deviation maps embedded in base64, the house style of :mod:`xmetro_ros.apps.report_html`) and the deviation maps
as files (``deviation_maps/*.png``). Both reports are rendered from the same report dict (``report.json``).

Deviation maps (:func:`deviation_maps`): for held-out scans (the coverage scans, else the calibration scans; with
no held-out scan, training scans, so labelled) each model set predicts the deviations of the scan's processed
points as the node does (one cloud, its sets, ``ModelSet.predict_with_uncertainty`` when calibrated). Each map is
a top view of the sphere (x, y relative to its centre, scan frame) in three panels on one signed µm scale: the
predicted and the actual deviation along the sphere's outward normal in the sign the node publishes (measured −
nominal: ``published_deviation`` of the target nominal − measured the model learns; with fitted positions the
centre is the fitted one) and their difference (actual − predicted). Next to it:
MAE per axis and along the normal, and where the model set is calibrated the share of actual errors within ±U per
axis. Needs matplotlib (the ``[train]`` extra, which training needs anyway).
"""

from __future__ import annotations

import base64
from pathlib import Path
from typing import Any

import numpy as np

from .report_html import _e, _table

__all__ = ["deviation_maps", "markdown", "write_html"]

AXES = ("x", "y", "z")
MAPS_PER_FAMILY = 2  # held-out scans drawn per model set
MAP_POINTS = 4000  # processed points per map (seeded subset)


def _pick(parts: dict[str, list[int]], n: int) -> tuple[str, list[int]]:
    for name in ("coverage", "calibration"):
        if parts.get(name):
            return name, parts[name][:n]
    return "train (no held-out scan)", parts["train"][:n]


def _map_png(rel: np.ndarray, panels: list[tuple[str, np.ndarray]], title: str) -> bytes:
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    vmax = float(np.nanpercentile(np.abs(np.concatenate([v for _, v in panels[:2]])), 99)) or 1.0
    # Fixed layout, one shared colour bar, no tight bounding box: layout engines cost seconds per figure.
    fig, axes = plt.subplots(1, len(panels), figsize=(3.6 * len(panels) + 1.0, 3.9), squeeze=False)
    fig.subplots_adjust(left=0.06, right=0.88, bottom=0.13, top=0.83, wspace=0.3)
    sc: Any = None
    for ax, (name, v) in zip(axes[0], panels, strict=True):
        ok = np.isfinite(v)
        sc = ax.scatter(rel[ok, 0], rel[ok, 1], c=v[ok], s=3, cmap="RdBu_r", vmin=-vmax, vmax=vmax,
                        rasterized=True)
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("x − centre [mm]", fontsize=8)
        ax.set_ylabel("y − centre [mm]", fontsize=8)
        ax.set_aspect("equal")
    fig.colorbar(sc, cax=fig.add_axes((0.9, 0.13, 0.015, 0.7)), label="error along the normal [µm]")
    fig.suptitle(title, fontsize=9)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80)
    plt.close(fig)
    return buf.getvalue()


def deviation_maps(data: Any, parts: dict[str, list[int]], model_dirs: dict[str, Path], out: Path, *,
                   seed: int = 0, n_maps: int = MAPS_PER_FAMILY, max_points: int = MAP_POINTS) -> list[dict[str, Any]]:
    """Write ``out/deviation_maps/<family>_r<rec>_s<scan>_<artifact>.png`` for held-out scans (module doc); return
    one record per map (family, scan, part, file, figures; ``png_b64`` for the HTML, not for JSON)."""
    from ..calibrate.dataset import sample_rows, scan_part
    from ..judge.features import STUDY_FEATURES
    from ..judge.inference import ModelSet
    from ..preprocess import PreprocessConfig, prepare_scan
    from ..scan.artifacts import Sphere
    from ..scan.targets import published_deviation

    part_name, picks = _pick(parts, n_maps)
    folder = out / "deviation_maps"
    folder.mkdir(parents=True, exist_ok=True)
    records = []
    for fam, d in model_dirs.items():
        ms = ModelSet.load(d)
        for i in picks:
            it = data.scans[i]
            sphere = it.scan.artifact
            assert isinstance(sphere, Sphere)
            prep = prepare_scan(it.scan, PreprocessConfig(), scanner=data.scanner)
            sel = sample_rows(np.random.default_rng(seed), len(prep), max_points)
            tp = scan_part(it.scan, prep, sel, STUDY_FEATURES)
            pts = np.asarray(prep.points if sel is None else prep.subset(sel).points, dtype=float)
            if ms.calibrated:
                r = ms.predict_with_uncertainty(tp.X)
                pred, U = np.asarray(r.errors, float), np.asarray(r.U, float)
            else:
                pred, U = np.asarray(ms.predict_with_sigma(tp.X)[0], float), None
            actual = np.asarray(tp.y, float)
            rel = pts - np.asarray(sphere.center, dtype=float)
            normal = rel / np.linalg.norm(rel, axis=1, keepdims=True)
            # shown in the published sign, measured − nominal (the MAEs and coverages do not depend on it)
            pn = published_deviation(np.einsum("ij,ij->i", pred, normal)) * 1e3
            an = published_deviation(np.einsum("ij,ij->i", actual, normal)) * 1e3
            ok = np.isfinite(pred).all(axis=1) & np.isfinite(actual).all(axis=1)
            rec: dict[str, Any] = {
                "family": fam, "scan": f"recording {it.recording} scan {it.index} {it.placement.artifact}",
                "part": part_name, "settings": it.scan.settings.label(), "n_points": int(ok.sum()),
                "mae_um": {ax: float(np.mean(np.abs(pred[ok, a] - actual[ok, a]))) * 1e3 for a, ax in enumerate(AXES)},
                "mae_normal_um": float(np.mean(np.abs(pn[ok] - an[ok]))),
                "mean_abs_actual_normal_um": float(np.mean(np.abs(an[ok]))),
                "within_U": None if U is None else
                {ax: float(np.mean(np.abs(actual[ok, a] - pred[ok, a]) <= U[ok, a])) for a, ax in enumerate(AXES)},
            }
            title = (f"{fam} · {rec['scan']} ({part_name}) · {rec['settings']} · MAE along the normal "
                     f"{rec['mae_normal_um']:.2f} µm")
            png = _map_png(rel[ok], [("predicted", pn[ok]), ("actual (measured − nominal)", an[ok]),
                                     ("actual − predicted", an[ok] - pn[ok])], title)
            f = folder / f"{fam}_r{it.recording}_s{it.index}_{it.placement.artifact}.png"
            f.write_bytes(png)
            rec["file"] = str(f.relative_to(out))
            rec["png_b64"] = base64.b64encode(png).decode("ascii")
            records.append(rec)
    return records


def _um(d: dict[str, Any], k: str) -> str:
    return f"{d[k]['max_abs'] * 1e3:.1f}" if k in d else "–"


def _vdi_rows(r: dict[str, Any]) -> list[list[Any]]:
    return [[s, _um(d, "PF_mm"), _um(d, "PS_mm"), _um(d, "SD_mm"), _um(d, "location_error_mm"),
             d.get("PF_mm", {}).get("n", 0)] for s, d in r["vdi2634"]["per_settings"].items()]


VDI_HEADER = ["settings", "PF", "PS", "SD", "location", "n"]


def _model_rows(r: dict[str, Any]) -> list[list[Any]]:
    rows = []
    for split, fams in r["models"].items():
        for fam, axes in fams.items():
            rows.append([split, fam, *[f"{axes[a]['mae']['mean'] * 1e3:.2f} (R² {axes[a]['r2']['mean']:.2f})"
                                       for a in AXES]])
    return rows


def _coverage_rows(r: dict[str, Any]) -> list[list[Any]]:
    rows = []
    for fam, d in r["uncertainty"]["families"].items():
        cov = d["coverage"]
        rows.append([fam, "/".join(f"{k:.2f}" for k in d["multiplier"]),
                     *[f"{cov[a]['coverage'] * 100:.1f} %" if "coverage" in cov[a] else "–" for a in AXES],
                     "/".join(f"{cov[a]['mean_U'] * 1e3:.1f}" if "mean_U" in cov[a] else "–" for a in AXES)])
    return rows


COVERAGE_HEADER = ["family", "multipliers x/y/z", "coverage X", "Y", "Z", "mean U X/Y/Z (µm)"]


def _map_row(m: dict[str, Any]) -> list[Any]:
    w = m["within_U"]
    return [m["family"], m["scan"], m["part"], m["n_points"], "/".join(f"{m['mae_um'][a]:.2f}" for a in AXES),
            f"{m['mae_normal_um']:.2f}", f"{m['mean_abs_actual_normal_um']:.2f}",
            "–" if w is None else "/".join(f"{w[a] * 100:.1f}" for a in AXES)]


MAP_HEADER = ["family", "scan", "part", "points", "MAE x/y/z (µm)", "MAE along the normal (µm)",
              "mean abs. actual along the normal (µm)", "within ±U x/y/z (%)"]


def _artifact_rows(c: dict[str, Any]) -> list[list[Any]]:
    rows = [[a["id"], "sphere", f"Ø {a['diameter_mm']:.4f}", f"{a['size_uncertainty_mm']:.4f}", a["certificate"]]
            for a in c["artifacts"]]
    rows += [[b["id"], f"ball bar {'–'.join(b['spheres'])}", f"L {b['distance_mm']:.4f}",
              f"{b['distance_uncertainty_mm']:.4f}", b["certificate"]] for b in c["ball_bars"]]
    return rows


def _check_lines(ch: dict[str, Any]) -> list[str]:
    src = {"scans": " (taken from the scans: nothing declared levels)", "campaign file": " (declared by the campaign "
           "file, each scanned)", "scanner description": " (declared by the scanner description, each scanned)"}
    return [f"{ch['n_measurements']} measurements from {ch['n_scans_read']} scans; per artifact {ch['per_artifact']}",
            f"settings levels {ch['settings_levels']}" + src.get(ch.get("levels_source", ""), ""),
            f"median angle estimated vs nominal normals {ch['median_normal_angle_deg']:.1f}°; largest free-fit "
            f"radius deviation {ch['radius_deviation_max_mm'] * 1e3:.1f} µm", *ch["notes"]]


def _prior_line(r: dict[str, Any]) -> str:
    p = r.get("prior")
    if not p:
        return "from random weights (no --prior)"
    return (f"{p['family']} warm-started from the prior {p['model_id']} ({p['dir']}, trained for scanner "
            f"{p['scanner']}), fine-tuned on the campaign's training scans")


def _md_table(header: list[str], rows: list[list[Any]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header),
            *["| " + " | ".join(str(c) for c in row) + " |" for row in rows]]


def markdown(r: dict[str, Any]) -> str:
    """``report.md`` from the report dict."""
    c = r["campaign"]
    lines = [f"# Calibration of scanner {c['scanner']['id']} (serial {c['scanner']['serial'] or '-'})", "",
             f"Campaign `{c['file']}` (sha256 `{c['sha256'][:16]}…`); positions: {r['positions']}. "
             f"Training: {_prior_line(r)}.",
             "", "## Certified artifacts", "",
             *_md_table(["id", "kind", "size (mm)", "U (mm)", "certificate"], _artifact_rows(c)),
             "", "## Data checks", "", *[f"- {x}" for x in _check_lines(r["checks"])],
             "", "## VDI/VDE 2634-2 figures per settings (largest |value|, µm)", "",
             *_md_table(VDI_HEADER, _vdi_rows(r)),
             "", "## Models (MAE µm, mean over the test draws; R²)", "",
             *_md_table(["split", "family", "X", "Y", "Z"], _model_rows(r))]
    u = r["uncertainty"]
    lines += ["", "## Interval coverage (95 %) on held-out scans", "", f"Split {u['split']}.", ""]
    if r["positions"] != "known":
        lines += ["Positions are fitted: coverage is judged on fitted-centre targets; location errors are in neither "
                  "the model nor its intervals (docs/calibration.md §7).", ""]
    if not u["families"]:
        lines.append("No uncertainty calibration (too few scans, or --no-uncertainty).")
    else:
        lines += _md_table(COVERAGE_HEADER, _coverage_rows(r))
    maps = r.get("deviation_maps") or []
    lines += ["", "## Deviation maps", "", "Predicted vs actual error along the sphere's normal, top view (report.html "
              "embeds them):", "", *_md_table([*MAP_HEADER, "file"], [[*_map_row(m), f"`{m['file']}`"] for m in maps])]
    return "\n".join(lines) + "\n"


_STYLE = ("body{font-family:sans-serif;max-width:1100px;margin:1em auto;color:#222}"
          "table{border-collapse:collapse;font-size:12px;margin:0.5em 0}"
          "td,th{border:1px solid #bbb;padding:3px 6px;text-align:right}th{background:#eee}"
          "td:first-child,th:first-child{text-align:left}"
          "pre{background:#f6f6f6;padding:0.6em;font-size:12px;white-space:pre-wrap}")


def write_html(path: str | Path, r: dict[str, Any], maps: list[dict[str, Any]]) -> Path:
    """Write the self-contained ``report.html`` (same content as report.md, maps embedded); return its path."""
    path = Path(path)
    c = r["campaign"]
    title = f"Calibration of scanner {c['scanner']['id']} (serial {c['scanner']['serial'] or '-'})"
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{_e(title)}</title><style>{_STYLE}</style>"
             f"</head><body><h1>{_e(title)}</h1>",
             _table(["item", "value"], [["campaign", f"{c['file']} (sha256 {c['sha256'][:16]}…)"],
                                        ["positions", r["positions"]], ["training", _prior_line(r)],
                                        ["wall time", f"{r['wall_s']:.0f} s"]]),
             "<h2>Certified artifacts</h2>",
             _table(["id", "kind", "size (mm)", "U (mm)", "certificate"], _artifact_rows(c)),
             "<h2>Data checks</h2><ul>" + "".join(f"<li>{_e(x)}</li>" for x in _check_lines(r["checks"])) + "</ul>",
             "<h2>VDI/VDE 2634-2 figures per settings (largest |value|, µm)</h2><p>PF: range of the radial residuals "
             "of a free-radius sphere fit (0.3 % largest dropped); PS: fitted − certified diameter; SD: fitted centre "
             "distance − calibrated ball-bar distance; location: |fitted − known centre| (known positions).</p>",
             _table(VDI_HEADER, _vdi_rows(r))]
    spacing = r["vdi2634"]["spacing"]
    if spacing:
        parts.append("<h3>Sphere spacing per scan</h3>" + _table(
            ["recording", "scan", "ball bar", "settings", "SD (µm)"],
            [[s["recording"], s["scan"], s["ball_bar"], s["settings"], f"{s['SD_mm'] * 1e3:.1f}"] for s in spacing]))
    parts.append("<details><summary>Probing figures per measurement</summary>" + _table(
        ["recording", "scan", "artifact", "settings", "position", "PF (µm)", "PS (µm)", "location (µm)", "points"],
        [[m["recording"], m["scan"], m["artifact"], m["settings"], m["position"], f"{m['PF_mm'] * 1e3:.1f}",
          f"{m['PS_mm'] * 1e3:.1f}", "–" if m["location_error_mm"] is None else f"{m['location_error_mm'] * 1e3:.1f}",
          m["n_points"]] for m in r["vdi2634"]["per_measurement"]]) + "</details>")
    parts += ["<h2>Models (MAE µm, mean over the test draws; R²)</h2>",
              _table(["split", "family", "X", "Y", "Z"], _model_rows(r))]
    u = r["uncertainty"]
    parts.append(f"<h2>Interval coverage (95 %) on held-out scans</h2><p>Split {_e(u['split'])}.</p>")
    if r["positions"] != "known":
        parts.append("<p>Positions are fitted: coverage is judged on fitted-centre targets; location errors are in "
                     "neither the model nor its intervals (docs/calibration.md §7).</p>")
    parts.append(_table(COVERAGE_HEADER, _coverage_rows(r)) if u["families"] else
                 "<p>No uncertainty calibration (too few scans, or --no-uncertainty).</p>")
    parts.append("<h2>Deviation maps</h2><p>Top view of the sphere (x, y relative to its centre, scan frame): the "
                 "predicted and the actual deviation along the outward normal (measured − nominal, as the node "
                 "publishes it) and their difference, "
                 "one signed µm scale per map.</p>")
    parts.append(_table(MAP_HEADER, [_map_row(m) for m in maps]))
    for m in maps:
        parts.append(f"<h3>{_e(m['family'])}: {_e(m['scan'])} ({_e(m['part'])}, {_e(m['settings'])})</h3>"
                     f"<img alt='deviation map {_e(m['file'])}' src='data:image/png;base64,{m['png_b64']}'/>")
    parts.append("</body></html>")
    path.write_text("\n".join(parts), encoding="utf-8")
    return path
