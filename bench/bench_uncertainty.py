"""Inference on a 180k-point scan (issues 13 and 14): the shipped default model's ``ModelSet.predict`` and
``predict_with_uncertainty`` (errors, σ̂ from the same ONNX run, U, Mahalanobis domain) against the implementation
before issue 13 (gather of the (M, F) rows into set order and a float64 scatter back; kept verbatim in
test/reference_inference.py), interleaved in one process; then, on the same contiguous sets, the number of sets per
ONNX Runtime run and the ONNX Runtime session options, each variant checked bit-identical to the shipped settings
before it is timed. The machine is shared and noisy: medians and minima of interleaved rounds, load average
recorded. Writes bench/results/uncertainty.json. Usage: ``python bench/bench_uncertainty.py [--reps N]``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from xmetro_ros.calibrate.dataset import build_table
from xmetro_ros.judge.features import STUDY_FEATURES
from xmetro_ros.judge.inference import ModelSet, session_options
from xmetro_ros.judge.set_kernels import to_sets
from xmetro_ros.scan.artifacts import Sphere
from xmetro_ros.scan.scanner import ScannerModel
from xmetro_ros.sim import simulate_scan

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "test"))
import reference_inference as ref  # noqa: E402

OUT = ROOT / "bench" / "results" / "uncertainty.json"
N = 180_000
CHUNKS = (32, 64, 128, 256, 512, 1024)


def interleaved(fns: dict, reps: int, pairs: dict | None = None) -> dict:
    """Run every function once per round, rounds repeated ``reps`` times (after one warm-up round), in a new seeded
    random order each round (a function can slow the next one: threads left spinning, caches): median and
    minimum ms of each; for each ``pairs`` entry name → (a, b), the median over rounds of a / b and a − b (ms)
    within the same round (steadier than ratios of medians when the load changes between rounds)."""
    for f in fns.values():
        f()
    t: dict[str, list[float]] = {k: [] for k in fns}
    keys = list(fns)
    rng = np.random.default_rng(0)
    for _ in range(reps):
        for i in rng.permutation(len(keys)):
            k = keys[i]
            f = fns[k]
            t0 = time.perf_counter()
            f()
            t[k].append(time.perf_counter() - t0)
    res: dict = {k: {"median_ms": round(float(np.median(v)) * 1e3, 1), "min_ms": round(float(np.min(v)) * 1e3, 1)}
                 for k, v in t.items()}
    for name, (a, b) in (pairs or {}).items():
        ta, tb = np.asarray(t[a]), np.asarray(t[b])
        res[name] = {"median_ratio": round(float(np.median(ta / tb)), 3),
                     "median_difference_ms": round(float(np.median(ta - tb)) * 1e3, 1)}
    return res


def features() -> np.ndarray:
    """(N, F) float32 features of an in-domain scan (the 55 mm sphere, study configuration 13), tiled to N rows."""
    sc = ScannerModel.load()
    scan = simulate_scan(Sphere(27.5), sc.study_configurations()[13], scanner=sc, seed=0)
    X = build_table([scan], list(STUDY_FEATURES), max_points_per_cloud=None).X
    return np.resize(X, (N, X.shape[1])).astype(np.float32)


def before_after(ms: ModelSet, X: np.ndarray, reps: int) -> dict:
    new_u = ms.predict_with_uncertainty(X)
    old_e, old_u, old_s, old_d = ref.predict_with_uncertainty(ms, X)
    same = {
        "predict": bool(np.array_equal(ms.predict(X), ref.predict(ms, X), equal_nan=True)),
        "errors": bool(np.array_equal(new_u.errors, old_e, equal_nan=True)),
        "sigma": bool(np.array_equal(new_u.sigma, old_s, equal_nan=True)),
        "U_max_rel_diff": float(np.nanmax(np.abs(new_u.U / old_u - 1))),
        "domain_distance_max_rel_diff": float(np.nanmax(np.abs(new_u.domain_distance / old_d - 1))),
    }
    from threadpoolctl import threadpool_limits

    from xmetro_ros.judge.pointsets import set_order

    order, pos = set_order(len(X), ms.set_size, ms.partition_seed)
    sets = to_sets(X, pos, order).reshape(-1, ms.set_size, X.shape[1])

    def blas2_before() -> None:  # as the node runs it: OPENBLAS_NUM_THREADS=2 (ros/rclpy_util.py)
        with threadpool_limits(2, user_api="blas"):
            ref.domain_distance_einsum(ms, X)

    def blas2_after() -> None:
        with threadpool_limits(2, user_api="blas"):
            ms.domain_distance(X)

    times = interleaved({
        "onnx_runs_only": lambda: ms._run_sets(sets, False),
        "onnx_runs_only_with_sigma": lambda: ms._run_sets(sets, True),
        "predict_before": lambda: ref.predict(ms, X),
        "predict_after": lambda: ms.predict(X),
        # before: the rows gathered and scattered, the distance's einsum loops of 0.7.2-0.7.3
        "with_uncertainty_before": lambda: ref.predict_with_uncertainty(ms, X, ref.domain_distance_einsum),
        "with_uncertainty_after": lambda: ms.predict_with_uncertainty(X),
        "domain_distance_before": lambda: ref.domain_distance_einsum(ms, X),
        "domain_distance_after": lambda: ms.domain_distance(X),
    }, reps, pairs={
        "domain_distance_after_vs_before": ("domain_distance_after", "domain_distance_before"),
        "predict_after_vs_before": ("predict_after", "predict_before"),
        "with_uncertainty_after_vs_before": ("with_uncertainty_after", "with_uncertainty_before"),
        "predict_after_vs_onnx_runs": ("predict_after", "onnx_runs_only"),
        "with_uncertainty_after_vs_onnx_runs": ("with_uncertainty_after", "onnx_runs_only_with_sigma"),
        "predict_before_vs_onnx_runs": ("predict_before", "onnx_runs_only"),
        "with_uncertainty_before_vs_onnx_runs": ("with_uncertainty_before", "onnx_runs_only_with_sigma"),
        "with_uncertainty_vs_predict_after": ("with_uncertainty_after", "predict_after"),
    })
    # apart: OpenBLAS's worker threads spin after the product and slow whatever runs next
    times.update(interleaved({"domain_distance_before_blas_2_threads": blas2_before,
                              "domain_distance_after_blas_2_threads_env": blas2_after}, reps))
    return {"identical": same, "times": times}


def _run(sess, sets: np.ndarray, chunk: int, outputs: list[str]) -> list[np.ndarray]:
    parts = [sess.run(outputs, {"X": sets[i : i + chunk]}) for i in range(0, len(sets), chunk)]
    return [np.concatenate([p[j] for p in parts]) for j in range(len(outputs))]


def onnx_variants(ms: ModelSet, X: np.ndarray, reps: int) -> dict:
    """Sets per run and session options on the contiguous sets of X; each variant's outputs compared bit for bit
    with the shipped settings' (a variant that changes a bit is reported and not kept)."""
    import onnxruntime as ort

    from xmetro_ros.judge.pointsets import set_order

    (member,) = [m for m in ms.members if m.kind == "sets"]
    order, pos = set_order(len(X), ms.set_size, ms.partition_seed)
    sets = to_sets(X, pos, order).reshape(-1, ms.set_size, X.shape[1])
    outs = list(member.outputs)
    base = _run(member.session, sets, ms.set_chunk, outs)

    def same(res: list[np.ndarray]) -> bool:
        return all(np.array_equal(a, b) for a, b in zip(res, base, strict=True))

    res: dict = {"shipped_chunk": ms.set_chunk, "chunks": {}, "options": {}}
    fns = {}
    for c in CHUNKS:
        res["chunks"][c] = {"identical": same(_run(member.session, sets, c, outs))}
        fns[f"chunk_{c}"] = lambda c=c: _run(member.session, sets, c, outs)
    fns["chunk_shipped_y_only"] = lambda: _run(member.session, sets, ms.set_chunk, outs[:1])
    for k, v in interleaved(fns, reps, pairs={"y_only_vs_both_outputs": ("chunk_shipped_y_only",
                                                                          f"chunk_{ms.set_chunk}")}).items():
        if k.startswith("chunk_") and k[6:].isdigit():
            res["chunks"][int(k[6:])].update(v)
        else:
            res[k] = v

    def variant(**kw) -> ort.InferenceSession:
        o = session_options(1)
        for key, val in kw.items():
            if key == "config":
                for ck, cv in val.items():
                    o.add_session_config_entry(ck, cv)
            else:
                setattr(o, key, val)
        return ort.InferenceSession(str(member.path), sess_options=o, providers=["CPUExecutionProvider"])

    L = ort.GraphOptimizationLevel
    sessions = {
        "shipped": member.session,
        "opt_disable_all": variant(graph_optimization_level=L.ORT_DISABLE_ALL),
        "opt_basic": variant(graph_optimization_level=L.ORT_ENABLE_BASIC),
        "opt_extended": variant(graph_optimization_level=L.ORT_ENABLE_EXTENDED),
        "opt_all": variant(graph_optimization_level=L.ORT_ENABLE_ALL),
        "no_mem_pattern": variant(enable_mem_pattern=False),
        "no_cpu_arena": variant(enable_cpu_mem_arena=False),
        "parallel_execution": variant(execution_mode=ort.ExecutionMode.ORT_PARALLEL),
        "threads_2": variant(intra_op_num_threads=2),
        "threads_2_no_spin": variant(intra_op_num_threads=2, config={"session.intra_op.allow_spinning": "0"}),
    }
    for k, s in sessions.items():
        res["options"][k] = {"identical": same(_run(s, sets, ms.set_chunk, outs))}
    vs_shipped = {f"{k}_vs_shipped": (k, "shipped") for k in sessions if k != "shipped"}
    for k, v in interleaved({k: (lambda s=s: _run(s, sets, ms.set_chunk, outs)) for k, s in sessions.items()},
                            reps, pairs=vs_shipped).items():
        res["options"].setdefault(k, {}).update(v)
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=15)
    ap.add_argument("--out", type=Path, default=OUT, help=f"results file (default {OUT.relative_to(ROOT)})")
    a = ap.parse_args(argv)
    X = features()
    ms = ModelSet.load(threads=1)
    res: dict = {"n_points": N, "reps": a.reps, "loadavg_before": os.getloadavg(),
                 "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS")}
    res["before_after"] = before_after(ms, X, a.reps)
    print(json.dumps(res["before_after"], indent=1), flush=True)
    res["onnx"] = onnx_variants(ms, X, a.reps)
    print(json.dumps(res["onnx"], indent=1), flush=True)
    res["loadavg_after"] = os.getloadavg()
    a.out.write_text(json.dumps(res, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
