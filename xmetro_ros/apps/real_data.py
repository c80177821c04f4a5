"""`xmetro real-data --out DIR`: the product on a real profilometer, end to end, scored against what the data say.

The data (``../shared/data/measured/profiler_sphere_r19_labelled``, read in place): 1,740 real profiles of a sphere
of radius 19.05 mm, the data set's training and validation lists (its own test split is held out: never read).

1. writes ``DIR/campaign.yaml`` (a profile campaign naming the **training list** only) and runs the documented
   ``xmetro calibrate`` path on it (:func:`~xmetro_ros.apps.calibrate_profiles.calibrate_profiles`) → ``DIR/cal``;
2. judges the **validation list** with the exported model set through ONNX Runtime
   (:class:`~xmetro_ros.judge.profile_model_set.ProfileModelSet`) and scores it
   (:mod:`xmetro_ros.calibrate.profile_metrics`): segmentation vs the labels, d vs the repeat-mean systematic
   estimate (repeats from both lists) next to the best constant and a per-5°-incidence-bin mean fitted on the
   training list, the same with d trained on **no repeat of a validation position** (what a new position gets),
   the per-axis coverage of U per 10° bin, U vs the repeat spread, the labels vs the product's flags, U as a
   quality score (ROC-AUC);
3. the same pipeline on the AT C5 profiles (another instrument: the r19 model applied as it is, figures whatever
   they are);
4. writes ``DIR/summary.json``, ``DIR/tables.md`` and ``DIR/*.png`` (docs/real-data.md quotes them; ``make
   real-data`` regenerates ``docs/results/real_data``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["R19_RADIUS_MM", "default_data_dir", "evaluate", "register", "run"]

R19_RADIUS_MM = 19.05
ATC5_RADIUS_MM = 40.0
UM = 1000.0


def default_data_dir(name: str) -> Path:
    """``../shared/data/measured/<name>`` beside the repository (or the working directory)."""
    for base in (Path(__file__).resolve().parents[2], Path.cwd()):
        p = base.parent / "shared" / "data" / "measured" / name
        if p.is_dir():
            return p
    return Path.cwd().parent / "shared" / "data" / "measured" / name


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``xmetro real-data``."""
    p = subparsers.add_parser("real-data", help="calibrate on real profiles of a certified sphere and score the "
                              "model on the held-out list", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default=None, help="the labelled profile data set (default: ../shared/data/measured/"
                   "profiler_sphere_r19_labelled)")
    p.add_argument("--atc5", default=None, help="the AT C5 profiles (default: ../shared/data/measured/"
                   "atc5_profiler_sphere_r40; 'none' to skip)")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--iterations", type=int, default=1000, help="CatBoost iterations of d")
    p.add_argument("--seed", type=int, default=0, help="seed of the segmentation, folds and fits (default 0)")
    p.set_defaults(func=run)


def _write_campaign(out: Path, data: Path) -> Path:
    import yaml

    out.mkdir(parents=True, exist_ok=True)
    doc = {"format": "xmetro-profile-campaign/1",
           "scanner": {"id": "profiler-r19", "serial": "unknown (Standard Sphere Seg data set V1)"},
           "artifact": {"id": "sphere_r19", "radius_mm": R19_RADIUS_MM,
                        "certificate": "standard sphere, radius 19.05 mm (data set README)"},
           # Relative to the campaign file: the same layout (the repository beside ../shared) reads it anywhere.
           "profiles": [{"list": os.path.relpath((data / "train_file.txt").resolve(), out.resolve())}]}
    path = out / "campaign.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def evaluate(model_dir: Path, data: Path, *, iterations: int, seed: int, log: Any = print) -> dict[str, Any]:
    """Score the model set on the validation list (module doc, step 2)."""
    from ..calibrate.profile_metrics import (
        bin_mean_baseline,
        coverage_table,
        quality_auc,
        segmentation_iou,
        systematic_scores,
    )
    from ..calibrate.profile_table import build_profile_table
    from ..judge.profile_model_set import ProfileModelSet
    from ..learn.profile_model import ProfileModel
    from ..scan.profiles import load_profile_list

    train = load_profile_list(data / "train_file.txt")
    val = load_profile_list(data / "val_file.txt")
    table = build_profile_table(train + val, R19_RADIUS_MM, seed=seed)
    val_names = {r.name for r in val}
    is_val_profile = np.array([n in val_names for n in table.names])
    vp = is_val_profile[table.profile]
    tp = ~vp
    ms = ProfileModelSet(model_dir)
    d = ms.predict(table.X)
    U = ms.uncertainty(table.X)
    log(f"validation: {int(is_val_profile.sum())} profiles, {int((vp & table.kept).sum())} sphere points kept")

    iou_val = segmentation_iou(table, np.flatnonzero(is_val_profile))
    iou_tr = segmentation_iou(table, np.flatnonzero(~is_val_profile))
    n_val_failed = sum(1 for n in table.failures if n in val_names)
    seg = {"val": {"profiles": len(iou_val), "median": float(np.median(iou_val)), "min": float(iou_val.min()),
                   "p5": float(np.percentile(iou_val, 5)), "below_0_5": int(np.sum(iou_val < 0.5)),
                   "no_arc": n_val_failed},
           "train": {"profiles": len(iou_tr), "median": float(np.median(iou_tr)), "min": float(iou_tr.min()),
                     "below_0_5": int(np.sum(iou_tr < 0.5))}}

    rows = vp & table.kept & (table.n_repeats >= 3)
    tr_rows = tp & table.kept
    base = bin_mean_baseline(table.angle[tr_rows], table.deviation[tr_rows], table.angle)
    sys_scores = systematic_scores(table.systematic[rows], d[rows], base[rows])
    meas_scores = systematic_scores(table.deviation[rows], d[rows], base[rows])
    # What a position never seen gets: d trained on the training list without any repeat of a validation position.
    val_pos = {table.positions[k] for k in np.flatnonzero(is_val_profile)}
    unseen_fit = tr_rows & ~np.isin(np.asarray(table.positions, dtype=object)[table.profile].astype(str),
                                    np.array(sorted(val_pos), dtype=str))
    d_new = ProfileModel(iterations=iterations, seed=seed).fit_regressor(table.X[unseen_fit],
                                                                         table.deviation[unseen_fit]).predict(table.X)
    base_new = bin_mean_baseline(table.angle[unseen_fit], table.deviation[unseen_fit], table.angle)
    new_scores = systematic_scores(table.systematic[rows], d_new[rows], base_new[rows])
    new_scores["training_profiles"] = len(np.unique(table.profile[unseen_fit]))
    by_bin = []
    b10 = np.clip(np.floor(np.abs(table.angle) / 10), 0, 8).astype(int)
    for k in range(9):
        s = rows & (b10 == k)
        if s.sum() < 50:
            continue
        sc = systematic_scores(table.systematic[s], d[s], base[s])
        by_bin.append({"bin_deg": [10 * k, 10 * k + 10], "points": int(s.sum()), "mae_d_um": sc["mae_d_um"],
                       "mae_zero_um": float(np.mean(np.abs(table.systematic[s]))) * UM,
                       "mae_bin_baseline_um": sc["mae_bin_baseline_um"],
                       "mae_d_new_position_um": float(np.mean(np.abs(table.systematic[s] - d_new[s]))) * UM,
                       "systematic_std_um": float(np.std(table.systematic[s])) * UM})

    cov_kept = coverage_table(table.deviation[vp & table.kept], d[vp & table.kept], U[vp & table.kept],
                              table.normals[vp & table.kept], table.angle[vp & table.kept],
                              table.spread[vp & table.kept])
    lab1 = vp & (table.label == 1)
    cov_label = coverage_table(table.deviation[lab1], d[lab1], U[lab1], table.normals[lab1], table.angle[lab1],
                               table.spread[lab1])
    near = np.abs(table.deviation) < 0.2
    pos_q = vp & (table.label == 0) & near
    neg_q = vp & (table.label == 1) & near
    quality = {"positives_label0_on_sphere": int(pos_q.sum()), "negatives_label1": int(neg_q.sum()),
               "auc_U": quality_auc(U, pos_q, neg_q), "auc_abs_incidence": quality_auc(np.abs(table.angle), pos_q,
                                                                                         neg_q)}
    border = table.on_arc & ~table.kept
    off = ~table.on_arc
    n_l1_file = int(table.label1_count[is_val_profile].sum()) if table.label1_count is not None else 0
    flags = {"kept_label1": int((vp & table.kept & (table.label == 1)).sum()),
             "kept_label0": int((vp & table.kept & (table.label == 0)).sum()),
             "border_label1": int((vp & border & (table.label == 1)).sum()),
             "border_label0": int((vp & border & (table.label == 0)).sum()),
             "off_arc_label1": int((vp & off & (table.label == 1)).sum()),
             "off_arc_label0": int((vp & off & (table.label == 0)).sum()),
             "label1_not_near_arc": n_l1_file - int(lab1.sum())}
    spread_kept = table.spread[vp & table.kept]
    return {"segmentation": seg, "systematic": sys_scores, "measured": meas_scores,
            "new_position": new_scores,
            "by_bin": by_bin, "coverage_kept": cov_kept, "coverage_label1": cov_label, "quality": quality,
            "flags_vs_labels": flags,
            "random_part": {"repeat_spread_rms_um": float(np.sqrt(np.nanmean(spread_kept ** 2))) * UM,
                            "repeat_spread_median_um": float(np.nanmedian(spread_kept)) * UM,
                            "systematic_std_um": float(np.nanstd(table.systematic[rows])) * UM,
                            "U_median_um": float(np.nanmedian(U[vp & table.kept])) * UM}}


def evaluate_atc5(model_dir: Path, atc5: Path, seed: int) -> dict[str, Any]:
    """The AT C5 profiles through the same segmentation, table and model (module doc, step 3)."""
    from ..calibrate.profile_metrics import coverage_table
    from ..calibrate.profile_table import build_profile_table
    from ..judge.profile_model_set import ProfileModelSet
    from ..scan.fitting import fit_sphere_center
    from ..scan.measured import load_atc5
    from ..scan.profiles import ProfileRecord

    profs = load_atc5(atc5)
    # The robot poses say where each laser plane cuts the sphere: its arc radius is sqrt(R² − y0²), y0 the
    # distance of the sphere's centre (fitted once over all profiles, certified radius) from the plane.
    base_pts = np.vstack([p.to_base() for p in profs])
    centre = fit_sphere_center(base_pts, ATC5_RADIUS_MM, loss="soft_l1", f_scale=0.05)
    pose_r = []
    for p in profs:
        T = np.asarray(p.flange_pose, dtype=float) @ np.asarray(p.hand_eye, dtype=float)
        y0 = float((centre - T[:3, 3]) @ T[:3, 1])
        pose_r.append(float(np.sqrt(max(ATC5_RADIUS_MM ** 2 - y0 ** 2, 0.0))))
    recs = [ProfileRecord(name=p.id, position=p.id, repeat=0, side=1, xz=np.asarray(p.xz, dtype=np.float64))
            for p in profs]
    table = build_profile_table(recs, ATC5_RADIUS_MM, seed=seed)
    ms = ProfileModelSet(model_dir)
    k = table.kept
    d = ms.predict(table.X[k])
    U = ms.uncertainty(table.X[k])
    dev = table.deviation[k]
    r19_ranges = ms.card.get("feature_ranges")
    fitted_r = dict(zip(table.names, table.arc_radius, strict=False))
    dr = [fitted_r[p.id] - pr for p, pr in zip(profs, pose_r, strict=False) if p.id in fitted_r]
    return {"profiles": len(recs), "with_arc": len(table.names), "failures": table.failures,
            "points_kept": int(k.sum()),
            "arc_radius_mm": [round(float(r), 3) for r in table.arc_radius],
            "arc_radius_from_poses_mm": [round(r, 3) for r in pose_r],
            "arc_radius_minus_pose_mm": {"median_abs": float(np.median(np.abs(dr))),
                                         "max_abs": float(np.max(np.abs(dr)))},
            "in_r19_domain": float(np.mean(ms.in_domain(table.X[k]))),
            "published_fraction": float(np.mean(np.isfinite(ms.publish(table.X[k])[0]))),
            "arc_rms_um": float(np.median(table.arc_rms)) * UM,
            "deviation_std_um": float(np.std(dev)) * UM,
            "mae_zero_um": float(np.mean(np.abs(dev - np.median(dev)))) * UM,
            "mae_d_um": float(np.mean(np.abs(dev - d))) * UM,
            "coverage": coverage_table(dev, d, U, table.normals[k], table.angle[k]),
            "range_w_mm": [float(table.X[k, 1].min()), float(table.X[k, 1].max())],
            "r19_feature_ranges": r19_ranges}


def _plots(out: Path, ev: dict[str, Any]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bins = ev["by_bin"]
    x = [b["bin_deg"][0] + 5 for b in bins]
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    ax[0].plot(x, [b["mae_zero_um"] for b in bins], "o-", label="zero")
    ax[0].plot(x, [b["mae_bin_baseline_um"] for b in bins], "s-", label="per-5° bin mean")
    ax[0].plot(x, [b["mae_d_um"] for b in bins], "^-", label="d (training list)")
    ax[0].plot(x, [b["mae_d_new_position_um"] for b in bins], "v--", label="d (no repeat of the position)")
    ax[0].set_xlabel("|in-plane incidence| (deg)")
    ax[0].set_ylabel("MAE vs repeat mean (µm)")
    ax[0].legend(fontsize=7)
    ax[0].set_title("systematic error, validation list")
    cb = ev["coverage_kept"]["bins"]
    xc = [b["bin_deg"][0] + 5 for b in cb]
    ax[1].plot(xc, [100 * b["coverage_x"] for b in cb], "o-", label="coverage x (%)")
    ax[1].plot(xc, [100 * b["coverage_z"] for b in cb], "s-", label="coverage z (%)")
    ax[1].axhline(95, color="grey", lw=0.8)
    ax2 = ax[1].twinx()
    ax2.plot(xc, [b["U_median_um"] for b in cb], "^-", color="C2", label="U median (µm)")
    ax2.plot(xc, [b.get("repeat_spread_rms_um") or np.nan for b in cb], "v-", color="C3", label="repeat spread (µm)")
    ax[1].set_xlabel("|in-plane incidence| (deg)")
    ax[1].set_ylabel("coverage (%)")
    ax[1].set_ylim(85, 100)
    ax2.set_ylim(0, None)
    ax2.set_ylabel("µm")
    ax[1].legend(fontsize=7, loc="lower left")
    ax2.legend(fontsize=7, loc="lower right")
    ax[1].set_title("U on the validation list")
    fig.tight_layout()
    fig.savefig(out / "real_data_by_incidence.png", dpi=110)
    plt.close(fig)


def _tables(ev: dict[str, Any], atc5: dict[str, Any] | None) -> str:
    s, n, seg = ev["systematic"], ev["new_position"], ev["segmentation"]["val"]
    lines = ["# Real profiler data: tables (generated by `xmetro real-data`)", "",
             f"Segmentation (validation, {seg['profiles']} profiles): IoU median {seg['median']:.3f}, 5th percentile "
             f"{seg['p5']:.3f}, min {seg['min']:.3f}, profiles below 0.5: {seg['below_0_5']}, without an arc: "
             f"{seg['no_arc']}.", "",
             "| systematic error (validation, repeat mean, µm) | points | MAE d | best constant | per-5° bin mean | "
             "d / constant | d / bin mean | R² d |", "|---|---|---|---|---|---|---|---|",
             f"| d trained on the training list | {s['points']} | {s['mae_d_um']:.2f} | "
             f"{s['mae_best_constant_um']:.2f} "
             f"| {s['mae_bin_baseline_um']:.2f} | {s['d_vs_constant']:.3f} | {s['d_vs_bin_baseline']:.3f} | "
             f"{s['r2_d']:.3f} |",
             f"| d trained without any repeat of a validation position | {n['points']} | {n['mae_d_um']:.2f} | "
             f"{n['mae_best_constant_um']:.2f} | {n['mae_bin_baseline_um']:.2f} | {n['d_vs_constant']:.3f} | "
             f"{n['d_vs_bin_baseline']:.3f} | {n['r2_d']:.3f} |", "",
             "| abs incidence (deg) | points | coverage x | coverage z | U median (µm) | p95 abs error (µm) | "
             "repeat spread RMS (µm) |", "|---|---|---|---|---|---|---|"]
    for b in ev["coverage_kept"]["bins"]:
        sp = b.get("repeat_spread_rms_um")
        lines.append(f"| {b['bin_deg'][0]:.0f}-{b['bin_deg'][1]:.0f} | {b['points']} | {100 * b['coverage_x']:.1f} % | "
                     f"{100 * b['coverage_z']:.1f} % | {b['U_median_um']:.1f} | {b['abs_error_p95_um']:.1f} | "
                     f"{'-' if sp is None else f'{sp:.1f}'} |")
    c = ev["coverage_kept"]
    q = ev["quality"]
    f = ev["flags_vs_labels"]
    lines += ["", f"Coverage over all kept points: x {100 * c['coverage_x']:.1f} %, z {100 * c['coverage_z']:.1f} % "
              f"({c['points']} points); on the label-1 points: x {100 * ev['coverage_label1']['coverage_x']:.1f} %, "
              f"z {100 * ev['coverage_label1']['coverage_z']:.1f} %.", "",
              f"Quality: ROC-AUC of U for label-0 points on the sphere ({q['positives_label0_on_sphere']}) vs label-1 "
              f"points ({q['negatives_label1']}): {q['auc_U']:.3f} (|incidence| alone: {q['auc_abs_incidence']:.3f}).",
              "", "| product \\ label | label 1 | label 0 |", "|---|---|---|",
              f"| kept (sphere) | {f['kept_label1']} | {f['kept_label0']} |",
              f"| border (on the arc, grazing) | {f['border_label1']} | {f['border_label0']} |",
              f"| near the arc, off it (outlier) | {f['off_arc_label1']} | {f['off_arc_label0']} |",
              f"| farther than 0.3 mm from the arc | {f['label1_not_near_arc']} | - |"]
    g = ev["geometry_sweep"]
    origins = ["parallel" if c["z_origin_mm"] is None else f"{c['z_origin_mm']:g}" for c in g["fan_origin"]]
    lines += ["", f"Geometry sweep (training list, {g['positions']} positions, {g['folds']} folds of positions, "
              "held-out MAE of d against the measured deviation; profile features alone "
              f"{g['profile_features_mae_um']:.2f} µm):",
              "", "| fan origin z (mm) | " + " | ".join(origins) + " |",
              "|---|" + "---|" * len(g["fan_origin"]),
              "| MAE (µm) | " + " | ".join(f"{c['mae_um']:.2f}" for c in g["fan_origin"]) + " |", "",
              "| camera tilt toward +y (deg) | " + " | ".join(f"{c['gamma_deg']:g}" for c in g["camera"]) + " |",
              "|---|" + "---|" * len(g["camera"]),
              "| MAE (µm), view angle added | " + " | ".join(f"{c['mae_um']:.2f}" for c in g["camera"]) + " |"]
    if atc5:
        cov = atc5["coverage"]
        lines += ["", f"AT C5 ({atc5['with_arc']} of {atc5['profiles']} profiles with an arc, "
                  f"{atc5['points_kept']} points; "
                  f"the r19 model as it is): MAE of the deviation about its median {atc5['mae_zero_um']:.1f} µm, "
                  f"MAE of (deviation − d) {atc5['mae_d_um']:.1f} µm, coverage x {100 * cov['coverage_x']:.1f} %, z "
                  f"{100 * cov['coverage_z']:.1f} %; arc RMS median {atc5['arc_rms_um']:.1f} µm; range coordinate "
                  f"{atc5['range_w_mm'][0]:.1f} to {atc5['range_w_mm'][1]:.1f} mm, inside the r19 model's training "
                  f"ranges: {100 * atc5['in_r19_domain']:.1f} % of the points. Arc radius fitted vs predicted by the "
                  "robot poses: "
                  f"median |difference| {atc5['arc_radius_minus_pose_mm']['median_abs']:.3f} mm, max "
                  f"{atc5['arc_radius_minus_pose_mm']['max_abs']:.3f} mm. Points the product would publish a d and U "
                  f"for (in the calibration's domain): {100 * atc5['published_fraction']:.1f} %."]
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    """``xmetro real-data`` (module doc); exit 2 with the reason when the data or the campaign cannot be used."""
    from ..calibrate.campaign_file import CampaignError
    from ..scan.measured import MeasuredDataError
    from ..scan.profiles import ProfileDataError
    from .calibrate_profiles import MODEL_NAME, calibrate_profiles

    t0 = time.perf_counter()
    data = Path(args.data) if args.data else default_data_dir("profiler_sphere_r19_labelled")
    out = Path(args.out)
    if not (data / "train_file.txt").is_file() or not (data / "val_file.txt").is_file():
        print(f"xmetro real-data: error: {data} holds no train_file.txt / val_file.txt (the labelled profile set)",
              file=sys.stderr)
        return 2
    try:
        camp = _write_campaign(out, data)
        calibrate_profiles(camp, out / "cal", iterations=args.iterations, seed=args.seed)
        mdir = out / "cal" / "models" / MODEL_NAME
        ev = evaluate(mdir, data, iterations=args.iterations, seed=args.seed)
        ev["geometry_sweep"] = json.loads((out / "cal" / "report.json").read_text())["scanner_geometry"]["sweep"]
        atc5 = None
        if args.atc5 != "none":
            a = Path(args.atc5) if args.atc5 else default_data_dir("atc5_profiler_sphere_r40")
            if a.is_dir():
                atc5 = evaluate_atc5(mdir, a, args.seed)
        ev["atc5"] = atc5
        ev["iterations"] = args.iterations
        ev["seconds"] = round(time.perf_counter() - t0, 1)
        (out / "summary.json").write_text(json.dumps(ev, indent=1))
        (out / "tables.md").write_text(_tables(ev, atc5))
        _plots(out, ev)
    except (CampaignError, ProfileDataError, MeasuredDataError, ValueError) as e:
        print(f"xmetro real-data: error: {e}", file=sys.stderr)
        return 2
    s = ev["systematic"]
    c = ev["coverage_kept"]
    print(f"real data: segmentation IoU median {ev['segmentation']['val']['median']:.3f}; MAE d {s['mae_d_um']:.2f} µm "
          f"vs constant {s['mae_best_constant_um']:.2f} and bin mean {s['mae_bin_baseline_um']:.2f}; new positions "
          f"{ev['new_position']['mae_d_um']:.2f} µm; coverage x {100 * c['coverage_x']:.1f} % z "
          f"{100 * c['coverage_z']:.1f} % (min bin {100 * c['min_bin_coverage']:.1f} %); quality AUC "
          f"{ev['quality']['auc_U']:.3f}; {ev['seconds']} s → {out}")
    return 0
