"""Inference with and without the uncertainty on a 180k-point scan (issue 14): ``ModelSet.predict`` (errors only)
against ``ModelSet.predict_with_uncertainty`` (errors, σ̂ from the same ONNX call, U, Mahalanobis domain) with the
shipped default model, 1 and 2 threads, best of 5, side by side in one run (the machine is shared and noisy: the
load average is recorded). Writes bench/results/uncertainty.json. The ratio is reported, not judged: the node
wiring (and its 100 ms budget with the extra outputs) comes later; measured here 1.2-1.5x of ``predict``."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from xmetro_ros.artifacts import Sphere
from xmetro_ros.dataset import build_table
from xmetro_ros.features import STUDY_FEATURES
from xmetro_ros.inference import ModelSet
from xmetro_ros.scanner import ScannerModel
from xmetro_ros.sim import simulate_scan

OUT = Path(__file__).resolve().parent / "results" / "uncertainty.json"
N = 180_000


def best_ms(fn, reps: int = 5) -> float:
    fn()
    best = np.inf
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return round(best * 1e3, 1)


def main() -> None:
    sc = ScannerModel.load()
    scan = simulate_scan(Sphere(27.5), sc.study_configurations()[13], scanner=sc, seed=0)
    X = build_table([scan], list(STUDY_FEATURES), max_points_per_cloud=None).X
    X = np.resize(X, (N, X.shape[1])).astype(np.float32)
    res = {"n_points": N, "loadavg_before": os.getloadavg()}
    for t in (1, 2):
        ms = ModelSet.load(threads=t)
        p = best_ms(lambda ms=ms: ms.predict(X))
        u = best_ms(lambda ms=ms: ms.predict_with_uncertainty(X))
        res[f"threads_{t}"] = {"predict_ms": p, "predict_with_uncertainty_ms": u, "ratio": round(u / p, 3)}
        print(f"threads {t}: predict {p} ms, with U {u} ms (x{u / p:.2f})")
    res["loadavg_after"] = os.getloadavg()
    OUT.write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
