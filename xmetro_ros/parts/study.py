"""Generalisation study on mesh parts never trained on: the virtual scanner scans a manufactured part (CAD + a
known form error, ``xmetro_ros.scan.generated_parts``), the product judges the scan (``ScanHandler.process``, the
node's path)
and its deviation map against the CAD, and the simulator's truth says how good each figure is.

Per part (presented rotated 5° about Z, shifted (0.37, 0.21) mm so no grid line falls on an edge, and raised
12 mm so its surface lies within the stand-offs the campaign covers, 62-90 mm: a part at the reference plane z 0
and below is out of the model's domain on the stand-off feature R_y, and the judge says so) and per
settings (three of the study's levels), with the model set given (default: the shipped one):

- prediction: MAE and p95 of |predicted − actual error| per axis (actual = nominal on the manufactured part −
  measured, noise included), next to the oracle floor (|expected − actual|, the simulator's noise-free error);
- intervals: coverage of |actual − predicted| ≤ U per axis, per region type (``regions.label_regions`` on the
  CAD: flat, curved, edge, concave, saddle), and in vs out of domain (flag OUT_OF_DOMAIN of the judge; also "any
  quality flag"); out-of-domain share;
- CAD deviation (``cad_judge.cad_deviation``, pose known): MAE and p95 of |measured − CAD − true form error| along
  the CAD normal, before and after compensation, and their ratio; again with best-fit registration (ICP from a
  start 0.3 mm / 0.5° off): the raw and the compensated scan each registered on its own against the truth = the
  true surface points (noise- and error-free) registered the same way; the fits, their uncertainty, and the
  compensated scan's pose against the true surface's.

Points: every point with a finite prediction except the simulator's injected outliers (their error is not the
scanner's law; the judge flags most of them as outliers anyway). Millimetres inside, µm in the report.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ..judge import flags as fl
from .regions import REGIONS

__all__ = ["DEFAULT_PARTS", "DEFAULT_SETTINGS", "PRESENTATION", "evaluate_part", "run_study"]

DEFAULT_PARTS = ("blade", "bowl", "step", "fillet", "saddle", "torus", "eggcrate")
#: (lateral_density /mm, direction_density /mm, exposure ms): low, default and high levels of the study
DEFAULT_SETTINGS = ((6.0, 3.0, 0.1), (10.0, 4.0, 0.5), (15.0, 5.0, 2.0))
FORM_UM = 40.0


def presentation() -> np.ndarray:
    """Part → scan frame transform of the study (4, 4): 5° about Z, then (0.37, 0.21, 12) mm."""
    a = np.radians(5.0)
    t = np.eye(4)
    t[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    t[:3, 3] = (0.37, 0.21, 12.0)
    return t


PRESENTATION = presentation()


def _cov(ok: np.ndarray, m: np.ndarray) -> dict[str, Any]:
    """Coverage of the rows ``m`` of ok (N, 3): per axis and mean, and the count."""
    n = int(m.sum())
    if n == 0:
        return {"n": 0, "coverage": None, "coverage_xyz": None}
    c = ok[m].mean(axis=0)
    return {"n": n, "coverage": float(c.mean()), "coverage_xyz": [float(x) for x in c]}


def _err_stats(r: np.ndarray) -> dict[str, list[float]]:
    a = np.abs(r)
    return {"mae_um": [float(x) for x in a.mean(axis=0) * 1e3],
            "p95_um": [float(x) for x in np.percentile(a, 95, axis=0) * 1e3]}


def evaluate_part(name: str, handler: Any, settings: Any, *, seed: int = 0, form_um: float = FORM_UM,
                  register: bool = True, keep_maps: bool = False, step_mm: float = 0.3,
                  head_rotation: np.ndarray | None = None) -> dict[str, Any]:
    """Simulate, judge and score one part at one setting (see the module docstring); returns a JSON-able dict
    (``maps`` with per-point arrays when ``keep_maps``). ``head_rotation`` (3×3, head frame): scanned from the
    looking-down start pose turned by it about the part's top (``sim.campaign.campaign_pose``, e.g. one of the
    recommender's orientations, ``pose_grid()``); None: looking down. ``judged_by``: the model set that judged it."""
    from ..scan.generated_parts import make_part
    from ..sim import simulate_scan
    from .cad_judge import cad_deviation, summary_um
    from .registration import perturbed

    cad = make_part(name, step_mm=step_mm)
    man = make_part(name, form_um=form_um, step_mm=step_mm).transformed(PRESENTATION)
    pose = None
    if head_rotation is not None:
        from ..sim.campaign import campaign_pose

        pose = campaign_pose(man, np.asarray(head_rotation, np.float64), handler.scanner)
    scan = simulate_scan(man, settings, scanner=handler.scanner, seed=seed, pose=pose)
    res = handler.process(scan)
    pts = np.asarray(res.scan.points, dtype=np.float64).reshape(-1, 3)
    pred = res.deviations
    U = res.uncertainty if res.uncertainty is not None else np.full_like(pred, np.nan)
    inj = (np.zeros(len(pts), bool) if scan.injected_outlier is None
           else np.asarray(scan.injected_outlier).reshape(-1))
    use = np.isfinite(pred).all(axis=1) & np.isfinite(pts).all(axis=1) & ~inj
    i = np.flatnonzero(use)
    p, e, u, flags = pts[i], pred[i], U[i], res.flags[i]
    actual = man.errors(p)
    expected = np.asarray(scan.expected_error).reshape(-1, 3)[i]
    region, _ = label_cad_regions(cad, p)
    ood = (flags & fl.FLAG_OUT_OF_DOMAIN) != 0
    # the shape part of the domain (mean curvature outside the calibration's shapes; U not widened there)
    full = np.zeros(len(pts), bool)
    if res.shape_out_of_domain is not None:
        full[np.asarray(res.prepared.index)] = res.shape_out_of_domain
    shape = full[i]
    anyq = (flags & (fl.QUALITY_BITS & ~fl.FLAG_OVER_TOLERANCE)) != 0
    ok = np.abs(actual - e) <= u
    model, oracle = _err_stats(e - actual), _err_stats(expected - actual)
    out: dict[str, Any] = {
        "part": name, "settings": [settings.lateral_density, settings.direction_density, settings.exposure_ms],
        "seed": seed, "form_um": form_um, "points": len(i), "judged_by": res.model_id,
        "injected_outliers_excluded": int(inj.sum()),
        # the scan's verdict as the node publishes it (ScanQuality), and why
        "verdict": res.quality["verdict_name"], "verdict_message": res.quality["message"],
        "model": model, "oracle": oracle,
        "mae_ratio_to_oracle": [m / o if o > 0 else None for m, o in zip(model["mae_um"], oracle["mae_um"],
                                                                          strict=True)],
        "coverage": {"all": _cov(ok, np.ones(len(i), bool)), "in_domain": _cov(ok, ~ood),
                     "out_of_domain": _cov(ok, ood), "no_quality_flag": _cov(ok, ~anyq),
                     "quality_flagged": _cov(ok, anyq),
                     "shape_in_domain": _cov(ok, ~shape), "shape_out_of_domain": _cov(ok, shape),
                     "regions": {r: {"all": _cov(ok, region == k), "in_domain": _cov(ok, (region == k) & ~ood),
                                     "out_of_domain": _cov(ok, (region == k) & ood)}
                                 for k, r in enumerate(REGIONS)}},
        "out_of_domain_share": float(ood.mean()) if len(i) else None,
        # where the misses are: share of the (point, axis) pairs outside U that the judge flags out of domain
        "misses_out_of_domain_share": float(ood[:, None].repeat(3, 1)[~ok].mean()) if (~ok).any() else None,
        "quality_flagged_share": float(anyq.mean()) if len(i) else None,
        "shape_out_of_domain_share": float(shape.mean()) if len(i) else None,
        "misses_shape_out_of_domain_share": float(shape[:, None].repeat(3, 1)[~ok].mean()) if (~ok).any() else None,
    }
    # Deviation map against the CAD, pose known; true form error along the CAD normal at the CAD point.
    dev = cad_deviation(cad, p, e, u, flags=flags, pose=PRESENTATION)
    form = np.einsum("ij,ij->i", man.project(dev.cad_points) - dev.cad_points, dev.normals)
    rb, ra = dev.before - form, dev.after - form
    cov_n = np.abs(ra) <= dev.u_normal
    out["cad"] = {"known_pose": _cad_scores(rb, ra, cov_n, ood, region), "u_normal": summary_um(dev.u_normal)}
    if register:
        # Best-fit registration, as a user without a fixture would do: the truth is then the deviation map of the
        # true (noise-free, error-free) surface points registered the same way; the product's maps are the raw and
        # the compensated scan, each registered on its own. A rigid fit absorbs what a rigid motion can of the form
        # error (the truth's datum) and of the scanner's error (the product's).
        init = perturbed(PRESENTATION, np.array([0.3, -0.2, 0.1]), np.array([0.3, -0.2, 0.5]))
        true_pts = man.project(p)
        dtrue = cad_deviation(cad, true_pts, np.zeros_like(e), None, pose=init, register=True)
        dreg = cad_deviation(cad, p, e, u, flags=flags, pose=init, register=True)
        draw = cad_deviation(cad, p, np.zeros_like(e), None, pose=init, register=True)
        assert dreg.registration is not None and draw.registration is not None and dtrue.registration is not None
        err = dreg.registration.pose @ np.linalg.inv(dtrue.registration.pose)
        out["cad"]["registered"] = _cad_scores(draw.before - dtrue.before, dreg.after - dtrue.before,
                                               np.abs(dreg.after - dtrue.before) <= dreg.u_normal, ood)
        out["cad"]["registered"]["registration"] = dreg.registration.to_dict()
        out["cad"]["registered"]["registration_raw"] = draw.registration.to_dict()
        out["cad"]["registered"]["registration_true"] = dtrue.registration.to_dict()
        out["cad"]["registered"]["pose_error"] = {  # compensated scan's registration vs the true surface's
            "translation_um": float(np.linalg.norm(err[:3, 3]) * 1e3),
            "rotation_deg": float(np.degrees(np.arccos(np.clip((np.trace(err[:3, :3]) - 1) / 2, -1, 1))))}
    if keep_maps:
        out["maps"] = {"points": p, "before": rb, "after": ra, "u_normal": dev.u_normal, "region": region,
                       "ood": ood, "shape_ood": shape, "covered": ok.all(axis=1)}
    return out


def label_cad_regions(cad: Any, points_scan: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Region labels of scan-frame points on the CAD (part frame): the points taken into the part frame."""
    from .regions import label_regions

    inv = np.linalg.inv(PRESENTATION)
    return label_regions(cad, points_scan @ inv[:3, :3].T + inv[:3, 3])


def _share(m: np.ndarray) -> float | None:
    return float(m.mean()) if len(m) else None


def _cad_scores(rb: np.ndarray, ra: np.ndarray, cov_n: np.ndarray, ood: np.ndarray,
                region: np.ndarray | None = None) -> dict[str, Any]:
    """MAE / p95 of the CAD deviation before and after compensation against the true form (µm), their factors,
    and the coverage of |after − true form| ≤ u_normal: all points, in domain and (``region`` labels given) per
    region type, all / in domain."""
    b = np.abs(rb[np.isfinite(rb)])
    a = np.abs(ra[np.isfinite(ra)])
    mb, ma = float(b.mean() * 1e3), float(a.mean() * 1e3)
    pb, pa = float(np.percentile(b, 95) * 1e3), float(np.percentile(a, 95) * 1e3)
    return {"before": {"mae_um": mb, "p95_um": pb}, "after": {"mae_um": ma, "p95_um": pa},
            "factor_mae": mb / ma if ma > 0 else None, "factor_p95": pb / pa if pa > 0 else None,
            "normal_coverage": float(cov_n.mean()), "normal_coverage_in_domain": _share(cov_n[~ood]),
            **({} if region is None else {"normal_coverage_regions": {
                r: {"n": int((region == k).sum()), "all": _share(cov_n[region == k]),
                    "in_domain": _share(cov_n[(region == k) & ~ood])} for k, r in enumerate(REGIONS)}})}


def _plot(part: str, maps: dict[str, np.ndarray], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keep = np.arange(0, len(maps["points"]), max(1, len(maps["points"]) // 15_000))  # a small PNG
    maps = {k: v[keep] for k, v in maps.items()}
    p = maps["points"]
    lim = float(np.percentile(np.abs(maps["before"]), 98) * 1e3)
    fig, ax = plt.subplots(1, 3, figsize=(12, 3.6), constrained_layout=True)
    for a, key, title in ((ax[0], "before", "measured − CAD − form, raw"),
                          (ax[1], "after", "… after compensation")):
        sc = a.scatter(p[:, 0], p[:, 1], c=maps[key] * 1e3, s=0.6, cmap="coolwarm", vmin=-lim, vmax=lim)
        a.set_title(f"{part}: {title}", fontsize=9)
        a.set_aspect("equal")
    fig.colorbar(sc, ax=ax[:2], label="µm", shrink=0.8)
    cols = np.array(["#999999", "#1f77b4", "#d62728", "#2ca02c", "#9467bd"])
    ax[2].scatter(p[:, 0], p[:, 1], c=cols[maps["region"]], s=0.6)
    bad = ~maps["covered"]
    ax[2].scatter(p[bad, 0], p[bad, 1], c="k", s=0.6, marker="x", linewidths=0.3)
    ax[2].set_title("regions: flat grey, curved blue, edge red, concave green, saddle purple\n"
                    "x: actual error outside U",
                    fontsize=8)
    ax[2].set_aspect("equal")
    for a in ax:
        a.set_xlabel("x (mm)")
    ax[0].set_ylabel("y (mm)")
    fig.savefig(path, dpi=72)
    plt.close(fig)


def run_study(out_dir: str | Path, *, model_dir: str | Path | None = None, parts: tuple[str, ...] = DEFAULT_PARTS,
              settings: tuple[tuple[float, float, float], ...] = DEFAULT_SETTINGS, seed: int = 0,
              plots: bool = True, log: Any = print) -> dict[str, Any]:
    """Run the study, write ``out_dir/<part>.json`` (one entry per settings), ``summary.json``, ``summary.md``,
    ``regions.md`` and (``plots``) ``<part>.png`` (deviation maps at the default settings). Returns the summary."""
    from ..judge.inference import ModelSet
    from ..judge.scan_handler import ScanHandler
    from ..scan.scanner import ScannerModel, ScanSettings

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    scanner = ScannerModel.load()
    handler = ScanHandler(ModelSet.load(model_dir), scanner)
    summary: dict[str, Any] = {"model": handler.model.id, "seed": seed, "form_um": FORM_UM, "parts": {}}
    for name in parts:
        rows = []
        for k, s in enumerate(settings):
            st = ScanSettings(*s)
            r = evaluate_part(name, handler, st, seed=seed + k, keep_maps=plots and s == (10.0, 4.0, 0.5))
            maps = r.pop("maps", None)
            if maps is not None:
                _plot(name, maps, out_dir / f"{name}.png")
            rows.append(r)
            kp = r["cad"]["known_pose"]
            if log:
                log(f"{name} {s}: {r['points']} pts, MAE/oracle {[f'{x:.2f}' for x in r['mae_ratio_to_oracle']]}, "
                    f"coverage {r['coverage']['all']['coverage']:.3f} (in-domain "
                    f"{r['coverage']['in_domain']['coverage']}), OOD {r['out_of_domain_share']:.3f}; CAD MAE "
                    f"{kp['before']['mae_um']:.2f} → {kp['after']['mae_um']:.2f} µm, p95 {kp['before']['p95_um']:.2f}"
                    f" → {kp['after']['p95_um']:.2f} µm")
        (out_dir / f"{name}.json").write_text(json.dumps(rows, indent=1))
        summary["parts"][name] = rows
    (out_dir / "summary.json").write_text(json.dumps(_condense(summary), indent=1))
    (out_dir / "summary.md").write_text(markdown(summary))
    (out_dir / "regions.md").write_text(markdown_regions(summary))
    return summary


def _pct(x: float | None) -> str:
    return "—" if x is None else f"{100 * x:.1f} %"


def markdown(summary: dict[str, Any]) -> str:
    """The tables of docs/parts-generalisation.md from a ``run_study`` summary."""
    lines = [f"Model set `{summary['model']}`, seed {summary['seed']}, form error ±{summary['form_um']:g} µm.", "",
             "| part | settings | points | MAE model / oracle X, Y, Z (µm) | coverage all / in / out of domain "
             "| out-of-domain share (points / misses) | CAD known pose: MAE, p95 before → after (µm) | factor MAE, p95 "
             "| registered: factor MAE, p95; pose error | verdict |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, rows in summary["parts"].items():
        for r in rows:
            c, kp, rg = r["coverage"], r["cad"]["known_pose"], r["cad"].get("registered")
            mae = ", ".join(f"{m:.2f} / {o:.2f}" for m, o in zip(r["model"]["mae_um"], r["oracle"]["mae_um"],
                                                                  strict=True))
            reg = (f"{rg['factor_mae']:.2f}, {rg['factor_p95']:.2f}; {rg['pose_error']['translation_um']:.0f} µm, "
                   f"{rg['pose_error']['rotation_deg']:.3f}°" if rg else "—")
            miss = r["misses_out_of_domain_share"]
            lines.append(
                f"| {name} | {'/'.join(f'{x:g}' for x in r['settings'])} | {r['points']} | {mae} | "
                f"{_pct(c['all']['coverage'])} / {_pct(c['in_domain']['coverage'])} / "
                f"{_pct(c['out_of_domain']['coverage'])} | {_pct(r['out_of_domain_share'])} / {_pct(miss)} | "
                f"{kp['before']['mae_um']:.2f} → {kp['after']['mae_um']:.2f}, {kp['before']['p95_um']:.2f} → "
                f"{kp['after']['p95_um']:.2f} | {kp['factor_mae']:.2f}, {kp['factor_p95']:.2f} | {reg} | "
                f"{r.get('verdict', '—')} |")
    lines += ["", "The shape part of the domain (mean curvature outside the calibration's shapes; U not widened "
              "there): coverage where the shape is in / out of the domain, and the out-of-domain share of the points "
              "and of the misses (point, axis pairs outside U):", "",
              "| part | settings | coverage shape in / out | shape out-of-domain share (points / misses) |",
              "|---|---|---|---|"]
    for name, rows in summary["parts"].items():
        for r in rows:
            c = r["coverage"]
            if "shape_in_domain" not in c:
                continue
            lines.append(f"| {name} | {'/'.join(f'{x:g}' for x in r['settings'])} | "
                         f"{_pct(c['shape_in_domain']['coverage'])} / {_pct(c['shape_out_of_domain']['coverage'])} | "
                         f"{_pct(r['shape_out_of_domain_share'])} / {_pct(r['misses_shape_out_of_domain_share'])} |")
    lines += ["", "Coverage per axis (|actual − d| ≤ U of each axis) and along the CAD normal (|after − true form| ≤ "
              "u_normal, pose known), all points / in domain:", "",
              "| part | settings | x | y | z | normal |", "|---|---|---|---|---|---|"]
    for name, rows in summary["parts"].items():
        for r in rows:
            c, kp = r["coverage"], r["cad"]["known_pose"]
            axes = [f"{_pct(a)} / {_pct(b)}" for a, b in zip(c["all"]["coverage_xyz"],
                                                             c["in_domain"]["coverage_xyz"] or [None] * 3,
                                                             strict=True)]
            lines.append(f"| {name} | {'/'.join(f'{x:g}' for x in r['settings'])} | " + " | ".join(axes)
                         + f" | {_pct(kp['normal_coverage'])} / {_pct(kp['normal_coverage_in_domain'])} |")
    return "\n".join(lines) + "\n"


def markdown_regions(summary: dict[str, Any]) -> str:
    """The coverage per region type (``regions.md``; a page of its own: with seven parts it would take
    ``summary.md`` over the docs' 3,000 words)."""
    lines = [f"Model set `{summary['model']}`, seed {summary['seed']}, form error ±{summary['form_um']:g} µm.", "",
             "Coverage per region type, all points / in domain: per axis x, y, z, then along the CAD normal "
             "(n = points of that region):", "",
              "| part | settings | " + " | ".join(REGIONS) + " |", "|---|---|" + "---|" * len(REGIONS)]
    for name, rows in summary["parts"].items():
        for r in rows:
            cells = []
            nreg = r["cad"]["known_pose"].get("normal_coverage_regions", {})
            for reg_name in REGIONS:
                g = r["coverage"]["regions"][reg_name]
                if not g["all"]["n"]:
                    cells.append("—")
                    continue
                xyz = ", ".join(f"{_pct(a)} / {_pct(b)}" for a, b in zip(
                    g["all"]["coverage_xyz"], g["in_domain"]["coverage_xyz"] or [None] * 3, strict=True))
                nr = nreg.get(reg_name)
                normal = f"; normal {_pct(nr['all'])} / {_pct(nr['in_domain'])}" if nr else ""
                cells.append(f"{xyz}{normal} (n {g['all']['n']})")
            lines.append(f"| {name} | {'/'.join(f'{x:g}' for x in r['settings'])} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _condense(summary: dict[str, Any]) -> dict[str, Any]:
    """The headline figures per part and settings (what docs/parts-generalisation.md quotes)."""
    out: dict[str, Any] = {k: v for k, v in summary.items() if k != "parts"}
    out["parts"] = {}
    for name, rows in summary["parts"].items():
        out["parts"][name] = [{
            "settings": r["settings"], "points": r["points"], "verdict": r.get("verdict"),
            "mae_ratio_to_oracle": r["mae_ratio_to_oracle"], "coverage": r["coverage"]["all"]["coverage"],
            "coverage_in_domain": r["coverage"]["in_domain"]["coverage"],
            "coverage_out_of_domain": r["coverage"]["out_of_domain"]["coverage"],
            "coverage_in_domain_xyz": r["coverage"]["in_domain"]["coverage_xyz"],
            "normal_coverage": r["cad"]["known_pose"]["normal_coverage"],
            "normal_coverage_in_domain": r["cad"]["known_pose"]["normal_coverage_in_domain"],
            "out_of_domain_share": r["out_of_domain_share"],
            "misses_out_of_domain_share": r["misses_out_of_domain_share"],
            "coverage_shape_in_domain": r["coverage"]["shape_in_domain"]["coverage"],
            "coverage_shape_out_of_domain": r["coverage"]["shape_out_of_domain"]["coverage"],
            "shape_out_of_domain_share": r["shape_out_of_domain_share"],
            "misses_shape_out_of_domain_share": r["misses_shape_out_of_domain_share"],
            "coverage_by_region": {k: v["all"]["coverage"] for k, v in r["coverage"]["regions"].items()},
            "region_points": {k: v["all"]["n"] for k, v in r["coverage"]["regions"].items()},
            "cad_known_pose": {k: r["cad"]["known_pose"][k] for k in ("before", "after", "factor_mae", "factor_p95")},
            "cad_registered": ({k: r["cad"]["registered"][k] for k in ("before", "after", "factor_mae", "factor_p95",
                                                                        "pose_error")}
                               if "registered" in r["cad"] else None),
        } for r in rows]
    return out
