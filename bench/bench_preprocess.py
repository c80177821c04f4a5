"""Pre-processing and feature timings on a 180k-point organized sphere scan (FEAT).

Measured side by side in one run (this machine is shared and noisy): the organized grid path (outliers + normals +
geometry), the study's 14 features, open3d's KD-tree normal estimation alone on the same points, and the
unorganized open3d path (dedupe + SOR + normals), on the plain cloud and with 78 % exact duplicates as in a real
bag. Writes bench/results/preprocess.json. Targets: grid ≤ 0.3 × open3d normals; unorganized ≤ 400 ms.
"""

from __future__ import annotations

import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from xmetro_ros import preprocess as pp
from xmetro_ros.artifacts import Sphere
from xmetro_ros.features import STUDY_FEATURES, FeatureContext, compute_features
from xmetro_ros.geometry import HeadPose
from xmetro_ros.scan import Scan
from xmetro_ros.scanner import ScannerModel, ScanSettings

OUT = Path(__file__).resolve().parent / "results" / "preprocess.json"


def sphere_scan(h: int = 500, w: int = 600, noise: float = 0.005) -> Scan:
    art = Sphere(27.5)
    ys = np.linspace(-28, 28, h)
    a = np.radians(np.linspace(-23, 23, w))
    d = np.stack([np.sin(a), 0 * a, -np.cos(a)], 1)
    o = np.zeros((h, w, 3))
    o[..., 1] = ys[:, None]
    o[..., 2] = 90
    dd = np.broadcast_to(d, (h, w, 3)).reshape(-1, 3)
    t = art.intersect(o.reshape(-1, 3), dd)
    p = o.reshape(-1, 3) + dd * (t + np.random.default_rng(0).normal(0, noise, len(t)))[:, None]
    return Scan(p.reshape(h, w, 3), ScanSettings(10, 4, 0.5), HeadPose.looking_down(90, y_mm=-28), "xm-ls90",
                artifact=art)


def best(fn, n: int = 7) -> tuple[float, float]:
    ts = []
    for _ in range(n):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return 1e3 * min(ts), 1e3 * float(np.median(ts))


def main() -> None:
    import open3d as o3d

    scanner = ScannerModel.load()
    scan = sphere_scan()
    flat, _, idx = scan.flat()
    res: dict = {"n_points": int(len(flat)), "grid": list(scan.shape), "cpus": os.cpu_count(),
                 "machine": platform.machine(), "unit": "ms (best, median of 7)"}
    prep = pp.prepare_scan(scan, scanner=scanner)
    res["grid_prepare"] = best(lambda: pp.prepare_scan(scan, scanner=scanner))
    res["grid_normals_only"] = best(lambda: pp.grid_normals(scan.points))
    res["grid_outliers_only"] = best(lambda: pp.grid_outliers(scan.points))
    res["features_14"] = best(lambda: compute_features(STUDY_FEATURES, FeatureContext.from_prepared(prep)))
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(flat))
    param = o3d.geometry.KDTreeSearchParamHybrid(radius=1.5, max_nn=30)
    res["open3d_normals_only"] = best(lambda: pc.estimate_normals(param), n=5)
    unorg = Scan(flat, scan.settings, scan.pose, scan.scanner_id)
    res["open3d_path_prepare"] = best(lambda: pp.prepare_scan(unorg, scanner=scanner), n=3)
    # a real bag: 78 % of the points are exact duplicates
    n_u = int(len(flat) * 0.22)
    rng = np.random.default_rng(1)
    dup = flat[:n_u][rng.integers(0, n_u, len(flat))]
    dup[:n_u] = flat[:n_u]
    res["open3d_path_prepare_78pct_duplicates"] = best(
        lambda: pp.prepare_scan(Scan(dup, scan.settings, scan.pose, scan.scanner_id), scanner=scanner), n=3)
    res["ratio_grid_prepare_to_open3d_normals"] = res["grid_prepare"][0] / res["open3d_normals_only"][0]
    true = scan.artifact.normals(flat)
    n_grid, q = pp.estimate_normals(flat, grid_shape=scan.shape, grid_index=idx, toward=true)
    n_o3d, _ = pp.estimate_normals(flat, toward=true)
    ang = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", n_grid, n_o3d), -1, 1)))
    res["grid_vs_open3d_deg"] = {"median": float(np.median(ang)), "p95": float(np.percentile(ang, 95)),
                                 "p95_quality_ge_0.9": float(np.percentile(ang[q >= 0.9], 95)),
                                 "p99": float(np.percentile(ang, 99))}
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(res, indent=2))
    print(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
