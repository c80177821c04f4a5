"""`xmetro calibrate PROFILE_CAMPAIGN --out DIR` for a campaign of single profiles (``format:
xmetro-profile-campaign/1``; :mod:`xmetro_ros.calibrate.profile_campaign`): a profilometer known only from its
data, one certified sphere.

1. read every profile the campaign's lists name (:mod:`xmetro_ros.scan.profiles`);
2. per profile, the product's segmentation finds the sphere's arc (no labels) and the table gives each arc point
   its deviation from the arc, its features and its repeat statistics (:mod:`xmetro_ros.calibrate.profile_table`);
3. fit the profile model (:mod:`xmetro_ros.learn.profile_model`): d on the sphere points kept, U calibrated on all
   arc points (border included, so that grazing points get their own, wider U), cross-fitted over positions;
4. write ``DIR/models/profile_catboost/`` (``model.onnx`` + ``card.json``, checked with ONNX Runtime) and
   ``DIR/report.json`` / ``DIR/report.md`` (profiles read and refused, segmentation IoU where the files carry
   labels, U per incidence bin).

Lengths mm in files, µm in the report's error figures.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["MODEL_NAME", "calibrate_profiles"]

MODEL_NAME = "profile_catboost"
#: Candidate laser-fan origins on the sensor axis (range coordinate, mm; None = parallel rays) and camera tilts
#: toward +y (deg) of the scanner-geometry sweep: a profilometer known only from its data says nothing of either.
FAN_ORIGINS_MM: tuple[float | None, ...] = (None, 300.0, 400.0, 600.0, 1000.0)
CAMERA_GAMMAS_DEG: tuple[float, ...] = (-30.0, -15.0, 0.0, 15.0, 30.0)
#: A candidate geometry counts as identified when it lowers the held-out MAE by more than this fraction.
IDENTIFIED_GAIN = 0.02


def scanner_geometry(table: Any, *, seed: int, iterations: int) -> dict[str, Any]:
    """The scanner description a profile campaign can support: laser plane = the sensor's x-z plane; fan origin
    and camera direction swept (``learn.profile_geometry``) on the kept points of half the positions; each is
    "identified" only when its best candidate beats the profile features alone by ``IDENTIFIED_GAIN``."""
    from ..learn.profile_geometry import geometry_sweep

    pid = table.position_ids()
    sw = geometry_sweep(table, table.kept & (pid % 2 == 0), fan_origins=list(FAN_ORIGINS_MM),
                        camera_gammas=list(CAMERA_GAMMAS_DEG), iterations=iterations, seed=seed)
    base = sw["profile_features_mae_um"]

    def verdict(rows: list[dict[str, Any]], key: str) -> dict[str, Any]:
        best = min(rows, key=lambda r: r["mae_um"])
        spread = max(r["mae_um"] for r in rows) - best["mae_um"]
        return {"best": best[key], "best_mae_um": best["mae_um"], "spread_um": spread,
                "identified": bool(best["mae_um"] < (1.0 - IDENTIFIED_GAIN) * base)}

    return {"laser_plane": "x-z plane of the sensor frame (x along the line, z the range axis)",
            "assumed": "parallel laser rays along the sensor axis; no camera term (a single profile has no "
                       "out-of-plane normal)",
            "fan_origin": verdict(sw["fan_origin"], "z_origin_mm"),
            "camera_tilt_deg": verdict(sw["camera"], "gamma_deg"),
            "sweep": sw}


def calibrate_profiles(campaign_path: str | Path, out: str | Path, *, iterations: int = 1000, seed: int = 0,
                       threads: int = 2, sweep: bool = True, log: Callable[[str], None] = print) -> dict[str, Any]:
    """Run the profile calibration (module doc); return the report dict. Raises CampaignError (bad campaign) or
    ProfileDataError (a profile file that cannot be read)."""
    from ..calibrate.campaign_file import CampaignError
    from ..calibrate.profile_campaign import load_profile_campaign
    from ..calibrate.profile_metrics import segmentation_iou
    from ..calibrate.profile_table import build_profile_table
    from ..learn.profile_model import ProfileModel
    from ..scan.profiles import load_profile_list

    t0 = time.perf_counter()
    out = Path(out)
    camp = load_profile_campaign(campaign_path)
    records = [r for pl in camp.lists for r in load_profile_list(pl.list_file, pl.root)]
    log(f"campaign {camp.path.name}: scanner {camp.scanner_id}, sphere {camp.artifact.id} "
        f"(R {camp.artifact.radius_mm:g} mm), {len(records)} profiles from {len(camp.lists)} list(s)")
    table = build_profile_table(records, camp.artifact.radius_mm, max_angle_deg=camp.border_angle_deg, seed=seed)
    if table.failures:
        log(f"{len(table.failures)} profiles hold no arc of the sphere and are left out (report.json lists them)")
    pos = table.position_ids()
    n_pos = len(np.unique(pos))
    if n_pos < 8:
        raise CampaignError(f"{camp.path}: {n_pos} sensor positions; the calibration needs 8 at least (U is "
                            "calibrated on positions the model did not see)")
    log(f"{len(table.names)} arcs, {int(table.kept.sum())} sphere points kept, {n_pos} positions; fitting d "
        f"(CatBoost, {iterations} iterations) and U (4 folds of positions)")
    model = ProfileModel(iterations=iterations, seed=seed, threads=threads)
    model.fit(table.X, table.deviation, pos, fit_rows=table.kept, calibration_rows=table.on_arc,
              feature_names=table.feature_names)
    geometry = None
    if sweep:  # the scanner description the data support: into the card as it is written, not patched after
        log("scanner geometry sweep: fan origins and camera directions, held out by position (half the positions)")
        geometry = scanner_geometry(table, seed=seed, iterations=min(iterations, 200))
    mdir = out / "models" / MODEL_NAME
    rng = np.random.default_rng(seed)
    check_rows = rng.choice(len(table), size=min(2000, len(table)), replace=False)
    scanner: dict[str, Any] = {"id": camp.scanner_id, "serial": camp.scanner_serial}
    if geometry is not None:
        scanner["geometry"] = geometry
    model.export(mdir, table.X[check_rows], extra_card={
        "scanner": scanner,
        "campaign": camp.card(), "trained_by": f"xmetro calibrate {camp.path.name} (profile campaign)",
        "training": {"profiles": len(table.names), "positions": n_pos, "points_fit": int(table.kept.sum()),
                     "points_calibration": int(table.on_arc.sum())}})
    iou = segmentation_iou(table, np.arange(len(table.names)))
    labelled = np.isfinite(iou)
    hw = model.half_width_mm_ if model.half_width_mm_ is not None else np.array([])
    report: dict[str, Any] = {
        "campaign": camp.card(), "model_dir": str(mdir),
        "profiles": {"read": len(records), "with_arc": len(table.names), "failures": table.failures,
                     "positions": n_pos, "arc_radius_mm": _pct(table.arc_radius),
                     "arc_rms_um": _pct(table.arc_rms * 1000.0)},
        "segmentation_iou": None if not labelled.any() else {
            "profiles": int(labelled.sum()), "median": float(np.median(iou[labelled])),
            "min": float(np.min(iou[labelled])), "below_0_5": int(np.sum(iou[labelled] < 0.5))},
        "uncertainty": model.card()["uncertainty"],
        "repeat_spread_rms_um": float(np.sqrt(np.nanmean(table.spread[table.kept] ** 2))) * 1000.0,
        "scanner_geometry": geometry,
        "seconds": round(time.perf_counter() - t0, 1),
    }
    report["u_um_by_bin"] = [None if not np.isfinite(v) else round(float(v) * 1000.0, 2) for v in hw]
    out.mkdir(parents=True, exist_ok=True)
    (out / "report.json").write_text(json.dumps(report, indent=1))
    (out / "report.md").write_text(_markdown(report))
    log(f"model set {mdir}; U (µm) by 10° bin of |incidence|: {report['u_um_by_bin']}; "
        f"{report['seconds']} s")
    return report


def _pct(a: np.ndarray) -> dict[str, float]:
    a = np.asarray(a, dtype=np.float64)
    return {"min": float(a.min()), "median": float(np.median(a)), "max": float(a.max())}


def _markdown(rep: dict[str, Any]) -> str:
    p = rep["profiles"]
    lines = [f"# Profile calibration: {rep['campaign']['scanner']['id']}, sphere {rep['campaign']['artifact']['id']}",
             "", f"- profiles read {p['read']}, with an arc of the sphere {p['with_arc']}, positions {p['positions']}",
             f"- arc radius (mm) min/median/max {p['arc_radius_mm']['min']:.2f} / {p['arc_radius_mm']['median']:.2f}"
             f" / {p['arc_radius_mm']['max']:.2f}; arc RMS (µm) median {p['arc_rms_um']['median']:.1f}",
             f"- repeat spread (random part), RMS over kept points: {rep['repeat_spread_rms_um']:.1f} µm"]
    if rep["segmentation_iou"]:
        s = rep["segmentation_iou"]
        lines.append(f"- segmentation vs the files' labels: IoU median {s['median']:.3f}, min {s['min']:.3f}, "
                     f"{s['below_0_5']} profiles below 0.5")
    lines += ["", "| abs incidence (deg) | calibration points | U (µm) | source |", "|---|---|---|---|"]
    u = rep["uncertainty"]
    for k, (c, h, src) in enumerate(zip(u["calibration_points"], rep["u_um_by_bin"], u["source"], strict=False)):
        lines.append(f"| {k * 10}-{k * 10 + 10} | {c} | {'-' if h is None else f'{h:.1f}'} | {src or 'none'} |")
    return "\n".join(lines) + "\n"
