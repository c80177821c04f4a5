#!/usr/bin/env python3
"""Conformal scores per surface class and scanned surface: ``python tools/class_scores.py [MODEL_DIR]``.

Why the shipped card's convex class is wider than a sphere alone needs (docs/uncertainty.md, "Per surface class"):
one 0.1 ms scan of every third calibration surface presentation (seed 1000, as the calibration) and three 0.1 ms
scans each of the spheres Ø35 and Ø45 and the cylinder r 20 mm, 4,000 kept points per scan; for every class ×
surface with ≥ 30 points seen within 30° of normal incidence, the 95 % quantile of the score |actual − d| / (σ̂ +
floor) per axis (the quantity the multipliers are quantiles of).
"""

from __future__ import annotations

import sys

import numpy as np

from xmetro_ros.judge.features import STUDY_FEATURES
from xmetro_ros.judge.inference import ModelSet
from xmetro_ros.judge.surface_class import SURFACE_CLASSES
from xmetro_ros.learn.calibration_set import calibration_set
from xmetro_ros.learn.uncertainty import predict_clouds
from xmetro_ros.scan.artifacts import Cylinder, Sphere
from xmetro_ros.scan.calibration_surfaces import surface_campaign
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings
from xmetro_ros.sim import simulate_scan


def main(model_dir: str | None = None) -> None:
    sc = ScannerModel.load()
    ms = ModelSet.load(model_dir) if model_dir else ModelSet.load()
    floor = float(ms.card["uncertainty"].get("sigma_floor_mm", 0.0))
    scans, labels = [], []
    for art, st, seed, label in [it for it in surface_campaign(sc, 1000, stride=1) if it[1].exposure_ms == 0.1][::3]:
        scans.append(simulate_scan(art, st, scanner=sc, seed=seed))
        labels.append(label.split()[1])  # "surface <name> tilt ..."
    for art, name in ((Sphere(22.5), "sphere45"), (Sphere(17.5), "sphere35"), (Cylinder(20.0), "cylinder20")):
        for k, st in enumerate((ScanSettings(6, 3, 0.1), ScanSettings(10, 5, 0.1), ScanSettings(15, 4, 0.1))):
            scans.append(simulate_scan(art, st, scanner=sc, seed=50 + k))
            labels.append(name)
    names = list(STUDY_FEATURES)
    cs = calibration_set(scans, names, max_points_per_cloud=4000, seed=1, scanner=sc)
    t = cs.table
    p = predict_clouds(ms, t.X, t.cloud_id, with_u=False)
    score = np.abs(t.y - p["errors"]) / (p["sigma"] + floor)
    inc = np.degrees(np.arccos(np.clip(t.X[:, names.index("Inc")], -1.0, 1.0)))
    cls = ms.surface_classes(cs.kappa)
    lab = np.array(labels)[t.cloud_id]
    print(f"model {ms.id} ({model_dir or 'packaged'}); 0.1 ms, incidence < 30 deg; q95 of |actual - d| / sigma")
    for c, cname in enumerate(SURFACE_CLASSES):
        for name in np.unique(lab):
            m = (cls == c) & (inc < 30) & (lab == name)
            if m.sum() >= 30:
                q = np.nanquantile(score[m], 0.95, axis=0)
                print(f"  {cname:8s} {name:11s} n {int(m.sum()):6d}  x {q[0]:.2f}  y {q[1]:.2f}  z {q[2]:.2f}")


if __name__ == "__main__":
    main(*sys.argv[1:2])
