"""The uncertainty acceptance experiment, reproducible: ``python -m xmetro_ros.learn.uncertainty_eval``.

Train a ``pointnet_multi`` (compact layout, spread head) on the 27 study configurations of two spheres (35, 55 mm)
and a cylinder (r 20 mm), campaign seed 1, 600 points per cloud; calibrate (split-conformal, crepes) on the same
artifacts simulated with seed 2 (whole clouds the model never saw); judge the 95 % intervals on a 45 mm sphere and
a 15 mm cylinder simulated with seed 3 (artifacts and seeds in neither) against the simulator's truth: coverage
per axis and per incidence-angle / exposure bin, mean U against the oracle half-width 1.96·noise_std, Spearman
rank correlation of U with the true std. test/test_uncertainty.py asserts the acceptance figures on this run.

``--shipped``: judge the packaged default model set instead (trained on spheres Ø35/45/55 and a cylinder r 20 mm,
campaign seed 0; calibrated on seed 1000 and on the calibration surfaces) on a sphere Ø40 and a cylinder r 15 mm
simulated with seed 3, each point's U of its surface class (``--all-class``: the all-class multipliers, as for a
point without a class).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np

from ..calibrate.dataset import build_table
from ..judge.features import STUDY_FEATURES
from ..judge.inference import AXES, ModelSet
from ..scan.artifacts import Cylinder, Sphere
from ..scan.scanner import ScannerModel
from ..sim.campaign import study_campaign
from .families import get_profile
from .train import export_model_set, fit_model
from .uncertainty import calibrate, interval_metrics, predict_clouds

__all__ = ["EXPOSURE_EDGES_MS", "INCIDENCE_EDGES_DEG", "bins_for", "markdown", "run"]

INCIDENCE_EDGES_DEG = np.array([0, 20, 35, 50, 60, 70, 80, 90.0])
EXPOSURE_EDGES_MS = np.array([0, 0.2, 1.0, 10.0])
TRAIN_ARTIFACTS = (Sphere(17.5), Sphere(27.5), Cylinder(20.0))
TEST_ARTIFACTS = (Sphere(22.5), Cylinder(15.0))
SHIPPED_TEST_ARTIFACTS = (Sphere(20.0), Cylinder(15.0))  # not in the full profile's campaign (Ø35/45/55, r 20)


def _table(artifacts, seed: int, per_cloud: int, scanner: ScannerModel):
    items = study_campaign(scanner, seed=seed, artifacts=list(artifacts))
    return build_table([it.simulate() for it in items], list(STUDY_FEATURES), max_points_per_cloud=per_cloud,
                       seed=seed)


def bins_for(X: np.ndarray, names: list[str]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Incidence angle (deg, from the feature Inc = cos) and exposure (ms) bins for interval_metrics."""
    inc = np.degrees(np.arccos(np.clip(X[:, names.index("Inc")], -1.0, 1.0)))
    return {"incidence_deg": (inc, INCIDENCE_EDGES_DEG),
            "exposure_ms": (X[:, names.index("exposure_time")], EXPOSURE_EDGES_MS)}


def run(out_dir: str | Path, epochs: int = 60, train_points: int = 600, seed: int = 0) -> dict[str, Any]:
    """Train, calibrate, evaluate (see the module doc); the model set goes to ``out_dir``. Returns the tables,
    the model set and the metrics."""
    sc = ScannerModel.load()
    names = list(STUDY_FEATURES)
    tr = _table(TRAIN_ARTIFACTS, 1, train_points, sc)
    cal = _table(TRAIN_ARTIFACTS, 2, 300, sc)
    te = _table(TEST_ARTIFACTS, 3, 400, sc)
    prof = dataclasses.replace(get_profile("quick"),
                               compact={"block1": (32,), "block2": (64,), "head": (32,), "epochs": int(epochs)})
    model = fit_model("pointnet_multi", tr.X, tr.y, seed=seed, profile=prof, groups=tr.cloud_id)
    d = export_model_set([model], out_dir, feature_names=names, X_train=tr.X, check_X=tr.X[tr.cloud_id == 0],
                         model_id=f"pointnet_multi-uncertainty-s{seed}")
    labels = [f"seed2/{c['label']}/{c['artifact']['kind']}" for c in cal.clouds]
    block = calibrate(d, cal.X, cal.y, cal.cloud_id, cloud_labels=labels)
    ms = ModelSet.load(d)
    pred = predict_clouds(ms, te.X, te.cloud_id)
    metrics = interval_metrics(pred["errors"], pred["U"], te.y, te.oracle_std, bins=bins_for(te.X, names))
    return {"train": tr, "cal": cal, "test": te, "dir": Path(d), "model_set": ms, "calibration": block,
            "pred": pred, "metrics": metrics}


def evaluate_shipped(model_dir: str | Path | None = None, surface_classes: bool = True) -> dict[str, Any]:
    """The shipped (or ``model_dir``) model set's calibrated intervals on SHIPPED_TEST_ARTIFACTS, seed 3.

    With ``surface_classes`` (and a card calibrated per surface class) each row takes the multiplier of its class,
    from the principal curvatures of its scan's grid (and its measured noise where the card takes it), as the node
    publishes U for an organized scan; without, every
    row takes the all-class multiplier, as for a point without a class (an unorganized scan, a scan border)."""
    from .calibration_set import calibration_set

    ms = ModelSet.load(model_dir)
    sc = ScannerModel.load()
    items = study_campaign(sc, seed=3, artifacts=list(SHIPPED_TEST_ARTIFACTS))
    # calibration_set draws the same rows as _table (build_table's draw) and gives each its surface class
    cs = calibration_set((it.simulate() for it in items), list(STUDY_FEATURES), max_points_per_cloud=400, seed=3,
                         scanner=sc)
    te = cs.table
    per_class = surface_classes and bool(ms.card["uncertainty"].get("conditional", {}).get("by_surface"))
    cls = ms.surface_classes(cs.kappa)
    pred = predict_clouds(ms, te.X, te.cloud_id, surface_class=cls if per_class else None,
                          noise=cs.noise if per_class else None)
    metrics = interval_metrics(pred["errors"], pred["U"], te.y, te.oracle_std,
                               bins=bins_for(te.X, list(STUDY_FEATURES)))
    return {"test": te, "model_set": ms, "calibration": ms.card["uncertainty"], "pred": pred, "metrics": metrics,
            "surface_class": cls, "per_class": per_class}


def markdown(metrics: dict, calibration: dict) -> str:
    """The docs tables: per axis coverage, widths, sharpness, rank correlation; conditional coverage by bin."""
    rows = ["| axis | multiplier | coverage | mean U (µm) | oracle half-width 1.96·σ (µm) | ratio | Spearman(U, σ) |",
            "|---|---|---|---|---|---|---|"]
    for a, ax in enumerate(AXES):
        m = metrics[ax]
        rows.append(f"| {ax.upper()} | {calibration['multiplier'][a]:.3f} | {100 * m['coverage']:.2f} % | "
                    f"{1e3 * m['mean_U']:.2f} | {1e3 * m['mean_oracle_half_width']:.2f} | "
                    f"{m['sharpness_ratio']:.3f} | {m['spearman_U_true_std']:.3f} |")
    for name in ("incidence_deg", "exposure_ms"):
        bins = metrics["x"]["bins"][name]
        rows += ["", f"| {name} bin | " + " | ".join(f"{ax.upper()} (n, coverage)" for ax in AXES) + " |",
                 "|---|" + "---|" * 3]
        for i, b in enumerate(bins):
            cells = []
            for ax in AXES:
                c = metrics[ax]["bins"][name][i]
                cells.append(f"{c['n']}, {100 * c['coverage']:.1f} %" if c["n"] else "0, -")
            rows.append(f"| {b['lo']:g}-{b['hi']:g} | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/uncertainty")
    ap.add_argument("--epochs", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--shipped", action="store_true", help="judge the packaged default model set (no training)")
    ap.add_argument("--all-class", action="store_true",
                    help="with --shipped: every point takes the all-class multipliers (no surface class)")
    a = ap.parse_args(argv)
    r = (evaluate_shipped(surface_classes=not a.all_class) if a.shipped
         else run(Path(a.out) / "model", epochs=a.epochs, seed=a.seed))
    text = markdown(r["metrics"], r["calibration"])
    Path(a.out).mkdir(parents=True, exist_ok=True)
    (Path(a.out) / "metrics.json").write_text(json.dumps({"metrics": r["metrics"], "calibration": r["calibration"]},
                                                         indent=1))
    (Path(a.out) / "tables.md").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
