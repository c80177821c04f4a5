"""The ROS-free judge (``ScanHandler.process``) at several thread budgets, with the time of each stage: the scaling
table of docs/performance.md. Needs numpy, numba, onnxruntime, scipy and PyYAML only (no rclpy, no open3d), so it
runs on a machine that has no ROS: the ``device`` tool's 16-core one.

Cases: the in-domain 55 mm sphere at 15/5/0.5 (~167k valid points), organized (rows = profiles) and unorganized
(the same points as one list: the kNN path). One ``ScanHandler`` per budget (its ``threads`` sets numba's kernels,
its model set's ONNX Runtime session gets the same number of intra-op threads), all loaded in one process; each
repetition judges every case at every budget in turn, so the budgets are compared on the same machine load.

Per stage (organized case, median ms per scan): the functions ``process`` calls, timed by wrapping them for the
length of the run (prepare = outliers + normals + geometry, its compiled parts listed as ``prepare.*``; features;
predict = the ONNX call with U; domain = the multivariate and shape domains; flags = the compiled per-point flags
and decisions; scatter = d, U and classes into the cloud's order; checks = the finite and working-volume masks,
the foreign-scan and single-profile checks; route = the choice of model set; summary = the verdict's statistics;
rest = what is left of ``process``). The outputs at every budget are compared with those at the first: the
deviations, U and flags must not depend on the thread count.

    python bench/bench_scaling.py [--threads 1,2,4,8,16] [--reps 7] [--out bench/results/scaling.json]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # numpy's BLAS stays out of the budget being measured
os.environ.setdefault("MALLOC_ARENA_MAX", "2")

import argparse
import importlib
import json
import platform
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
OUT = ROOT / "bench" / "results" / "scaling.json"

# the machine's description and the median / p90 / min figures of the other thread benchmark (ROS-free imports;
# bench_threads sets OMP_NUM_THREADS to every CPU before bench_node's default of 2)
from bench_threads import _cpu_model  # noqa: E402
from bench_threads import bn as _bench_node  # noqa: E402

_ms = _bench_node._ms

#: (module, attribute, stage name): the functions of ``ScanHandler.process`` that the stage profile times. Modules
#: whose callers import the name inside a function (at call time) are patched where the name lives.
MODULE_STAGES = (
    ("xmetro_ros.preprocess", "prepare_scan", "prepare"),
    ("xmetro_ros.preprocess.grid_kernels", "planes", "prepare.planes"),
    ("xmetro_ros.preprocess.grid_kernels", "grid_outliers", "prepare.outliers"),
    ("xmetro_ros.preprocess.grid_kernels", "kept_normals", "prepare.normals"),
    ("xmetro_ros.preprocess.prepare", "_knn_unorganized", "prepare.knn"),
    ("xmetro_ros.preprocess.prepare", "point_geometry", "prepare.geometry"),
    ("xmetro_ros.preprocess.grid_kernels", "orient_rows", "prepare.orient"),
    ("xmetro_ros.judge.features", "compute_features", "features"),
    ("xmetro_ros.judge.scan_handler", "kept_point_flags", "flags"),
    ("xmetro_ros.judge.scan_handler", "scatter_kept", "scatter"),
    ("xmetro_ros.judge.scan_handler", "point_masks", "checks"),
    ("xmetro_ros.judge.scan_handler", "base_flags", "flags"),
    ("xmetro_ros.judge.scan_handler", "foreign_scan_reason", "checks"),
    ("xmetro_ros.judge.scan_handler", "single_profile_reason", "checks"),
)
MODEL_STAGES = (("predict_with_uncertainty", "predict"), ("out_of_domain_mv", "domain"))
HANDLER_STAGES = (("_shape_out_of_domain", "domain"), ("route", "route"), ("summarize", "summary"))


class StageTimer:
    """Times the stage functions while active (``with timer:``); ``record()`` closes one judged scan."""

    def __init__(self, handler: Any) -> None:
        self.handler, self.acc = handler, defaultdict(float)
        self.scans: list[dict[str, float]] = []
        self._saved: list[tuple[Any, str, Any, bool]] = []

    def _wrap(self, fn: Any, name: str) -> Any:
        acc = self.acc

        def timed(*a: Any, **k: Any) -> Any:
            t = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                acc[name] += time.perf_counter() - t
        return timed

    def __enter__(self) -> StageTimer:
        for mod, attr, name in MODULE_STAGES:
            m = importlib.import_module(mod)
            fn = getattr(m, attr)
            self._saved.append((m, attr, fn, False))
            setattr(m, attr, self._wrap(fn, name))
        for obj, stages in ((self.handler.model, MODEL_STAGES), (self.handler, HANDLER_STAGES)):
            for attr, name in stages:
                self._saved.append((obj, attr, None, True))
                setattr(obj, attr, self._wrap(getattr(obj, attr), name))
        return self

    def __exit__(self, *exc: Any) -> None:
        for obj, attr, fn, instance in reversed(self._saved):
            if instance:
                delattr(obj, attr)  # the instance attribute goes; the class's method shows again
            else:
                setattr(obj, attr, fn)
        self._saved.clear()

    def record(self, total_s: float) -> None:
        row = dict(self.acc)
        top = sum(v for k, v in row.items() if "." not in k)
        row["rest"] = total_s - top
        row["process"] = total_s
        self.scans.append(row)
        self.acc.clear()

    def medians_ms(self) -> dict[str, float]:
        keys = sorted({k for s in self.scans for k in s}, key=lambda k: (k.split(".")[0], k))
        return {k: round(float(np.median([s.get(k, 0.0) for s in self.scans])) * 1e3, 1) for k in keys}


def _cases() -> dict[str, Any]:
    from xmetro_ros.scan.artifacts import Sphere
    from xmetro_ros.scan.scan import Scan
    from xmetro_ros.scan.scanner import ScanSettings
    from xmetro_ros.sim import simulate_scan

    big = simulate_scan(Sphere(27.5, np.zeros(3)), ScanSettings(15.0, 5.0, 0.5), seed=0, stamp_ns=10**9)
    pts, fields, _ = big.flat()
    unorg = Scan(points=pts, settings=big.settings, pose=big.pose, scanner_id=big.scanner_id, fields=fields,
                 stamp_ns=10**9)
    return {"organized_180k": big, "unorganized_180k": unorg}


def _outputs(res: Any) -> dict[str, np.ndarray]:
    return {"deviations": np.asarray(res.deviations), "uncertainty": np.asarray(res.uncertainty),
            "flags": np.asarray(res.flags)}


def _differences(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> dict[str, float]:
    """Largest |difference| of the deviations and U (mm; NaN where both are NaN counts as equal) and the share of
    points whose flags differ."""
    out: dict[str, float] = {}
    for k in ("deviations", "uncertainty"):
        x, y = a[k], b[k]
        if not np.array_equal(np.isnan(x), np.isnan(y)):
            out[f"{k}_nan_pattern_differs"] = 1.0
        both = np.isfinite(x) & np.isfinite(y)
        out[f"{k}_max_abs_diff_mm"] = float(np.abs(x[both] - y[both]).max()) if both.any() else 0.0
    out["flags_differ_fraction"] = float(np.mean(a["flags"] != b["flags"]))
    return out


def measure(counts: list[int], reps: int, model_dir: str) -> dict:
    from xmetro_ros.judge.inference import ModelSet
    from xmetro_ros.judge.scan_handler import HandlerParams, ScanHandler
    from xmetro_ros.scan.scanner import ScannerModel

    cases = _cases()
    scanner = ScannerModel.load(None)
    t0 = time.perf_counter()
    handlers = {t: ScanHandler(ModelSet.load(model_dir or None, threads=t), scanner, HandlerParams(threads=t))
                for t in counts}
    load_s = time.perf_counter() - t0
    judge: dict = {(t, k): [] for t in counts for k in cases}
    onnx: dict = {t: [] for t in counts}
    reference: dict = {}
    diffs: dict = {}
    timers = {t: StageTimer(h) for t, h in handlers.items()}
    X = None
    for i in range(reps + 1):  # the first round warms up (and compiles what the cache does not hold)
        for k, scan in cases.items():
            for t, h in handlers.items():
                a = time.perf_counter()
                res = h.process(scan)
                dt = time.perf_counter() - a
                assert res.quality["verdict_name"] == "OK", res.quality["message"]
                if i == 0:
                    outs = _outputs(res)
                    ref = reference.setdefault(k, outs)
                    diffs[f"{k}@{t}"] = _differences(ref, outs)
                    if X is None and k == "organized_180k":
                        X = res.features
                else:
                    judge[(t, k)].append(dt)
        for t, h in handlers.items():
            a = time.perf_counter()
            h.model.predict_with_uncertainty(X)
            if i:
                onnx[t].append(time.perf_counter() - a)
            with timers[t]:
                a = time.perf_counter()
                h.process(cases["organized_180k"])
                total = time.perf_counter() - a
            if i:
                timers[t].record(total)
            else:
                timers[t].acc.clear()
    out: dict = {"handlers_load_s": round(load_s, 2), "rows_judged": len(X), "threads": {}}
    for t in counts:
        row: dict = {k: _ms(judge[(t, k)]) for k in cases}
        row["onnx_call"] = _ms(onnx[t])
        row["stages_organized_ms"] = timers[t].medians_ms()
        row["outputs_vs_first_budget"] = {k: diffs[f"{k}@{t}"] for k in cases}
        out["threads"][str(t)] = row
        print(f"threads {t}: organized {row['organized_180k']['median_ms']} ms, unorganized "
              f"{row['unorganized_180k']['median_ms']} ms, ONNX call {row['onnx_call']['median_ms']} ms; "
              f"stages {row['stages_organized_ms']}", flush=True)
    t1, tn = str(counts[0]), str(counts[-1])
    for k in cases:
        out[f"speedup_{k}_{t1}_to_{tn}"] = round(out["threads"][t1][k]["median_ms"]
                                                 / out["threads"][tn][k]["median_ms"], 2)
    out["speedup_onnx_call"] = round(out["threads"][t1]["onnx_call"]["median_ms"]
                                     / out["threads"][tn]["onnx_call"]["median_ms"], 2)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", default="1,2", help="comma-separated budgets, ascending (default 1,2)")
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--model", default="", help="model set directory (default: the shipped default model)")
    ap.add_argument("--machine", default="", help="what the machine is, in words (recorded with the figures)")
    ap.add_argument("--out", default=str(OUT))
    args = ap.parse_args(argv)
    counts = [int(c) for c in args.threads.split(",")]
    import numba
    import onnxruntime

    from xmetro_ros.compute.threads import available_cpus, max_threads

    result: dict = {"machine": {"name": args.machine, "cpu": _cpu_model(), "cpus_available": available_cpus(),
                                "numba_threads_max": max_threads(), "python": platform.python_version(),
                                "numpy": np.__version__, "numba": numba.__version__,
                                "onnxruntime": onnxruntime.__version__},
                    "goal": {"speedup_1_to_16_threads": 4.0}, "reps": args.reps,
                    **measure(counts, args.reps, args.model)}
    result["machine"]["threading_layer"] = numba.threading_layer()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
