"""The judge at several thread budgets (the node's ``threads``: numba's kernels and ONNX Runtime together), measured
side by side in one process, interleaved with open3d's normals of the same points, with the time of each stage.

Cases: the in-domain 55 mm sphere at 15/5/0.5 (~167k valid points), organized (rows = profiles) and unorganized
(the same points as one list: the kNN path). Each repetition judges every case at every budget in turn, then times
open3d's ``estimate_normals`` (hybrid radius 1 mm, 30 neighbours, open3d's own threads) on the same points, so the
ratios compare runs that saw the same machine load.

Stages (organized case, median ms, the same judge cut where ``bench_node.stages`` cuts it): decode (cloud →
scan), prepare (outliers, normals, geometry), features, predict (ONNX call, U included), flags_summary (the rest of
``ScanHandler.process``), outputs (the published clouds).

    python bench/bench_threads.py [--threads 1,2] [--reps 9] [--out bench/results/threads.json]

``make bench`` runs it at 1 and 2 threads on this machine. On a bigger one without ROS (the ``device`` tool, when
one is lent) bench/bench_scaling.py measures the ROS-free judge at 1/2/4/8/16 threads: the scaling table of
docs/node.md (bench/results/scaling_16core.json).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # numpy's BLAS stays out of the budget being measured
os.environ.setdefault("OMP_NUM_THREADS", str(os.cpu_count() or 1))  # open3d's normals: every core (bench_node: 2)
os.environ.setdefault("MALLOC_ARENA_MAX", "2")

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import bench_node as bn  # noqa: E402

OUT = ROOT / "bench" / "results" / "threads.json"


def _core(threads: int, model_dir: str):
    from xmetro_ros.ros.core import XmetroCore
    from xmetro_ros.ros.params import PARAMS

    values = {p.name: p.default for p in PARAMS}
    values["model_dir"], values["threads"] = model_dir, threads
    core = XmetroCore(values)
    if core.model is None:
        raise SystemExit(f"bench_threads: {core.degraded}")
    return core


def _stages(core, msg, scan) -> dict[str, float]:
    """One judge of ``msg`` cut into its stages (seconds)."""
    from xmetro_ros.compute.threads import use_threads
    from xmetro_ros.judge.features import FeatureContext, compute_features
    from xmetro_ros.preprocess import prepare_scan
    from xmetro_ros.ros.convert import cloud_to_scan

    h = core.handler
    # numba's count is the calling thread's and the last judge (another budget's core) left its own: the stages
    # timed alone must run at this core's, as its process does
    use_threads(h.params.threads)
    t0 = time.perf_counter()
    sc = cloud_to_scan(msg, scan.settings, scan.pose, scan.scanner_id)
    t1 = time.perf_counter()
    prep = prepare_scan(sc, h.preprocess_config(), scanner=h.scanner)
    t2 = time.perf_counter()
    X = compute_features(list(core.model.feature_names), FeatureContext.from_prepared(prep), dtype=np.float32)
    t3 = time.perf_counter()
    core.model.predict_with_uncertainty(X)
    t4 = time.perf_counter()
    h.process(sc)
    t5 = time.perf_counter()
    core.judge(msg)
    t6 = time.perf_counter()
    process = t5 - t4
    return {"decode": t1 - t0, "prepare": t2 - t1, "features": t3 - t2, "predict": t4 - t3,
            "flags_summary": process - (t2 - t1) - (t3 - t2) - (t4 - t3),
            "outputs": (t6 - t5) - process - (t1 - t0)}


def measure(counts: list[int], reps: int, model_dir: str) -> dict:
    from xmetro_ros.compute.threads import resolve_threads
    from xmetro_ros.ros.convert import scan_to_cloud, settings_to_msg
    from xmetro_ros.scan.scan import Scan

    big = bn._sim(bn.BIG, stamp_ns=10**9)
    pts, fields, _ = big.flat()
    unorg = Scan(points=pts, settings=big.settings, pose=big.pose, scanner_id=big.scanner_id, fields=fields,
                 stamp_ns=10**9)
    cases = {"organized_180k": big, "unorganized_180k": unorg}
    msgs = {k: scan_to_cloud(s) for k, s in cases.items()}
    cores = {t: _core(t, model_dir) for t in counts}
    for core in cores.values():
        core.add_settings(settings_to_msg(big.settings, big.pose, "artifact", 1, big.scanner_id))
    judge: dict = {(t, k): [] for t in counts for k in cases}
    o3d: dict = {k: [] for k in cases}
    stage: dict = {t: [] for t in counts}
    for i in range(reps + 1):  # the first round warms up
        for k, scan in cases.items():
            for t, core in cores.items():
                a = time.perf_counter()
                res = core.judge(msgs[k])
                dt = time.perf_counter() - a
                assert res.deviations is not None, res.quality.message
                if i:
                    judge[(t, k)].append(dt)
            ot = bn._o3d_normals_s(scan.flat()[0])
            if i:
                o3d[k].append(ot)
        for t, core in cores.items():
            st = _stages(core, msgs["organized_180k"], big)
            if i:
                stage[t].append(st)
    out: dict = {"threads": {}}
    for t in counts:
        row: dict = {"resolved": resolve_threads(t)}
        for k in cases:
            med = float(np.median(judge[(t, k)]))
            row[k] = {**bn._ms(judge[(t, k)]), "ratio_to_open3d_normals": round(med / float(np.median(o3d[k])), 3)}
        row["stages_organized_ms"] = {s: round(float(np.median([d[s] for d in stage[t]])) * 1e3, 1)
                                      for s in stage[t][0]}
        out["threads"][str(t)] = row
        print(f"threads {t}: organized {row['organized_180k']['median_ms']} ms "
              f"({row['organized_180k']['ratio_to_open3d_normals']}x open3d), unorganized "
              f"{row['unorganized_180k']['median_ms']} ms ({row['unorganized_180k']['ratio_to_open3d_normals']}x); "
              f"stages {row['stages_organized_ms']}", flush=True)
    out["open3d_normals"] = {k: bn._ms(v) for k, v in o3d.items()}
    t1, tn = str(counts[0]), str(counts[-1])
    out["speedup_organized"] = round(out["threads"][t1]["organized_180k"]["median_ms"]
                                     / out["threads"][tn]["organized_180k"]["median_ms"], 2)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", default="1,2", help="comma-separated budgets, ascending (default 1,2)")
    ap.add_argument("--reps", type=int, default=9)
    ap.add_argument("--model", default="", help="model set directory (default: the shipped default model)")
    ap.add_argument("--out", default=str(OUT))
    args = ap.parse_args(argv)
    counts = [int(c) for c in args.threads.split(",")]
    import numba

    from xmetro_ros.compute.threads import available_cpus, max_threads

    result = {"machine": {"cpu": bn.cpu_model(), "utc": bn.utc_now(), "cpus_available": available_cpus(),
                          "numba_threads_max": max_threads(),
                          "python": platform.python_version()},
              "goals": {"ratio_to_open3d_normals_at_2_threads": 0.5, "unorganized_ratio_at_2_threads": 1.2,
                        "speedup_1_to_16_threads": 4.0},
              "reps": args.reps, **measure(counts, args.reps, args.model)}
    result["machine"]["threading_layer"] = numba.threading_layer()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
