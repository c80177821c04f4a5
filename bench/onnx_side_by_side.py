"""How the PointNet's chunks of sets run side by side best (a one-off measurement for docs/performance.md, kept to be
rerun): ONNX Runtime runs of the shipped model on the 55 mm sphere's 3,326 sets, on 1..16 threads, with (a) one
session shared by the threads (what ModelSet does), (b) one session per thread, (c) a shared session without its CPU
memory arena, (d) ONNX Runtime's own intra-op threads on one run per chunk (what ModelSet did before), and chunks
of 1, 2, 4 or 8 per thread. Median ms of 7 after a warm-up.

    python bench/onnx_side_by_side.py [--threads 1,4,8,16] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv: list[str] | None = None) -> int:
    import onnxruntime as ort

    from xmetro_ros.compute.threads import parallel_for
    from xmetro_ros.judge.inference import ModelSet, _to_sets, session_options, set_order

    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", default="1,4,8,16")
    ap.add_argument("--out", default="")
    args = ap.parse_args(argv)
    ms = ModelSet.load()
    m = ms.members[0]
    rng = np.random.default_rng(5)
    lo, hi = ms.domain
    X = (lo + (hi - lo) * rng.uniform(0.0, 1.0, size=(166_269, len(lo)))).astype(np.float32)
    order, pos = set_order(len(X), ms.set_size, ms.partition_seed)
    sets = _to_sets(X, pos, order).reshape(-1, ms.set_size, X.shape[1])
    k, n, _ = sets.shape

    def session(threads: int = 1, arena: bool = True):
        o = session_options(threads)
        o.enable_cpu_mem_arena = arena
        return ort.InferenceSession(str(m.path), sess_options=o, providers=["CPUExecutionProvider"])

    def run(sess_for, threads: int, per_thread: int) -> float:
        y = np.empty((2, k, n, 3), np.float32)
        chunk = 128 if per_thread == 0 else max(1, min(128, -(-k // (per_thread * threads))))

        def one(c: int) -> None:
            s = sess_for()
            x = sets[c * chunk : (c + 1) * chunk]
            io = s.io_binding()
            io.bind_input("X", "cpu", 0, np.float32, x.shape, x.ctypes.data)
            for o, name in enumerate(m.outputs):
                dst = y[o, c * chunk : c * chunk + len(x)]
                io.bind_output(name, "cpu", 0, np.float32, (len(x), n, 3), dst.ctypes.data)
            s.run_with_iobinding(io)

        ts = []
        for i in range(8):
            a = time.perf_counter()
            parallel_for(one, -(-k // chunk), threads)
            if i:
                ts.append(time.perf_counter() - a)
        return round(float(np.median(ts)) * 1e3, 2)

    import threading

    out: dict = {"sets": k, "results": {}}
    shared = session()
    no_arena = session(arena=False)
    for t in [int(x) for x in args.threads.split(",")]:
        local = threading.local()

        def own(local: threading.local = local):
            if not hasattr(local, "s"):
                local.s = session()
            return local.s

        row = {f"shared_x{p}": run(lambda: shared, t, p) for p in (1, 2, 4, 8)}
        row["per_thread_session_x4"] = run(own, t, 4)
        row["shared_no_arena_x4"] = run(lambda: no_arena, t, 4)
        intra = session(t)
        row["intra_op_one_caller_chunk128"] = run(lambda intra=intra: intra, 1, 0)  # one caller, chunks of 128
        out["results"][str(t)] = row
        print(t, row, flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
