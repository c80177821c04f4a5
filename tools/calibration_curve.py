"""Few scans, good model: the learning curve of a foreign scanner's model with and without the virtual prior.

Writes ``docs/results/calibration_curve.json`` (table in docs/calibration.md, "Few scans"). Run once::

    .venv/bin/python tools/calibration_curve.py [--seeds 0,1,2] [--sizes 1,2,4,8,16]

- The foreign scanner: test/test_calibrate.py's data sheet (200 mm stand-off, 20° triangulation, 45° fan,
  camera on −y) with test/test_calibrate_e2e.py's effect magnitudes (centroid and stand-off effects ×2, edge
  ×0.5, speckle ×0.8): the "real" scanner, simulated.
- The virtual prior: a ``pointnet_multi`` (compact layout of the quick profile, spread head) trained on a campaign
  simulated with a virtual scanner RE-PARAMETERISED to the data sheet's geometry but with the packaged virtual
  scanner's effect magnitudes (a data sheet gives the geometry, not the effects): 25.4 mm spheres at the origin,
  27 settings (lateral 4/5/6, direction 2/2.5/3,
  exposure 0.2/0.5/2 ms: the recorded scans' levels lie within) × the campaign's pose.
- Recorded scans: the foreign scanner's scans of two 25.4 mm balls placed off-origin (known centres), settings
  cycling through 4 levels; the first n of 16 train, 8 further scans judge.
- For each n: from scratch (the family's fit on the n scans) and fine-tuned (the prior's network as warm start,
  ``PointNetRegressor(warm_start=...)``, same epochs). Accuracy: MAE over the 3 axes on the judged scans, and its
  ratio to the oracle floor = MAE of the simulator's noise-free expected error as a predictor of the actual error
  at the same points.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RADIUS = 12.7
CENTRES = [(30.0, -8.0, 0.0), (-32.0, 6.0, 2.0)]
LEVELS = [(4.0, 2.0, 0.5), (6.0, 3.0, 2.0), (4.0, 3.0, 0.2), (6.0, 2.0, 0.5)]
SHEET = {"id": "ls-200", "serial": "SN-7", "measuring_range_mm": [150.0, 250.0], "field_of_view_mm": [100.0, 180.0],
         "triangulation_angle_deg": 20.0, "camera_side": "-y",
         "settings_range": {"lateral_density": [0.5, 100], "direction_density": [0.1, 50], "exposure_ms": [0.005, 50]},
         "default_settings": {"lateral_density": 4.0, "direction_density": 2.0, "exposure_ms": 0.5}}


def foreign_effects(default: dict) -> dict:
    """test_calibrate_e2e.foreign_effects: the default magnitudes with a few changed."""
    eff = json.loads(json.dumps(default))
    eff["centroid"]["coefficient_mm"] *= 2.0
    eff["standoff"]["linear_mm"] *= 2.0
    eff["edge"]["max_mm"] *= 0.5
    eff["speckle"]["sigma_mm"] *= 0.8
    return eff


def _scores(reg, table) -> dict:
    pred = reg.predict(table.X, groups=table.cloud_id)
    mae = float(np.abs(pred - table.y).mean())
    floor = float(np.abs(table.oracle - table.y).mean())
    return {"mae_um": round(mae * 1e3, 3), "ratio_to_floor": round(mae / floor, 3)}


def main(argv: list[str] | None = None) -> int:
    from xmetro_ros.calibrate.dataset import build_table
    from xmetro_ros.judge.features import STUDY_FEATURES
    from xmetro_ros.learn.families import get_profile
    from xmetro_ros.learn.pointnet import PointNetRegressor
    from xmetro_ros.learn.train import _pointnet_config
    from xmetro_ros.scan.artifacts import Sphere
    from xmetro_ros.scan.scanner import ScannerModel, ScanSettings
    from xmetro_ros.sim import simulate_scan
    from xmetro_ros.sim.campaign import study_campaign

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", default="0,1,2", help="independent repetitions (prior, scans, fits); means reported")
    ap.add_argument("--sizes", default="1,2,4,8,16")
    ap.add_argument("--out", default=str(ROOT / "docs" / "results" / "calibration_curve.json"))
    args = ap.parse_args(argv)
    sizes = [int(s) for s in args.sizes.split(",")]
    seeds = [int(s) for s in args.seeds.split(",")]
    t0 = time.perf_counter()
    default = ScannerModel.load().effects
    real = ScannerModel.from_dict({**SHEET, "effects": foreign_effects(default)}, "ls-200 (simulated real)")
    virtual = ScannerModel.from_dict({**SHEET, "effects": default}, "ls-200 (virtual, data-sheet geometry)")
    prof = get_profile("quick")
    cfg = _pointnet_config("pointnet_multi", prof, threads=1)
    feats = list(STUDY_FEATURES)

    def one(seed: int) -> tuple[list[dict], float, int]:
        grid = [ScanSettings(a, b, c) for a in (4.0, 5.0, 6.0) for b in (2.0, 2.5, 3.0) for c in (0.2, 0.5, 2.0)]
        items = study_campaign(scanner=virtual, seed=seed + 500, sphere_diameters=(2 * RADIUS,), cylinder=False,
                               configurations=grid)
        prior_table = build_table([it.simulate() for it in items], feats, max_points_per_cloud=2000, seed=seed,
                                  scanner=virtual)
        prior = PointNetRegressor(cfg, seed=seed).fit(prior_table.X, prior_table.y, prior_table.cloud_id)
        print(f"prior: {len(items)} virtual clouds, {len(prior_table)} points ({time.perf_counter() - t0:.0f} s)",
              flush=True)

        def recorded(k: int, seed: int):
            return simulate_scan(Sphere(RADIUS, CENTRES[k % 2]), ScanSettings(*LEVELS[(k // 2) % len(LEVELS)]),
                                 scanner=real, seed=seed + k)

        pool = [recorded(k, seed + 10_000) for k in range(max(sizes))]
        judge = build_table([recorded(k, seed + 20_000) for k in range(8)], feats, max_points_per_cloud=2000,
                            seed=seed + 1, scanner=real)
        rows: list[dict] = [{"n_scans": 0, "prior_only": _scores(prior, judge)}]
        print(rows[-1], flush=True)
        for n in sizes:
            tab = build_table(pool[:n], feats, max_points_per_cloud=2000, seed=seed, scanner=real)
            scratch = PointNetRegressor(cfg, seed=seed).fit(tab.X, tab.y, tab.cloud_id)
            tuned = PointNetRegressor(cfg, seed=seed, warm_start=prior.module_).fit(tab.X, tab.y, tab.cloud_id)
            rows.append({"n_scans": n, "scratch": _scores(scratch, judge), "virtual_prior": _scores(tuned, judge)})
            print(rows[-1], flush=True)
        return rows, float(np.abs(judge.oracle - judge.y).mean()), len(items)

    runs = {seed: one(seed) for seed in seeds}
    keys = [("prior_only",)] + [("scratch", "virtual_prior")] * len(sizes)
    mean_rows = []
    for i, ks in enumerate(keys):
        row: dict = {"n_scans": runs[seeds[0]][0][i]["n_scans"]}
        for k in ks:
            row[k] = {m: round(float(np.mean([runs[sd][0][i][k][m] for sd in seeds])), 3)
                      for m in ("mae_um", "ratio_to_floor")}
        mean_rows.append(row)
    out = {"description": __doc__.split("\n\n")[0], "seeds": seeds, "profile": "quick (pointnet_multi compact)",
           "epochs": cfg.epochs, "n_prior_clouds": runs[seeds[0]][2], "n_judged_scans": 8,
           "oracle_floor_um": round(float(np.mean([r[1] for r in runs.values()])) * 1e3, 3), "curve_mean": mean_rows,
           "per_seed": {str(sd): r[0] for sd, r in runs.items()},
           "wall_s": round(time.perf_counter() - t0, 1)}
    Path(args.out).write_text(json.dumps(out, indent=1))
    print(f"wrote {args.out} ({out['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
