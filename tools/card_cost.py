#!/usr/bin/env python3
"""What a card costs the judge: ``python tools/card_cost.py OTHER_MODEL_DIR [--reps 9]``.

The ROS-free judge (``ScanHandler.process``, the node's path) on the bench scan of ``bench/bench_node.py`` (the
55 mm sphere at 15/5/0.5, ~167k valid points, organized), with the shipped model set and with ``OTHER_MODEL_DIR``
side by side in one process, interleaved, one numba and ONNX Runtime thread (the node's default on 2 cores).
Prints the median and minimum per scan (ms) and the median of the paired ratios shipped / other. E.g. the card
before the surface classes (0.7.2's, the same ONNX model):

    git archive 7ab7cde xmetro_ros/models/default | tar -x -C /tmp/card072
    python tools/card_cost.py /tmp/card072/xmetro_ros/models/default
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("other", type=Path, help="the model set directory to compare the shipped one with")
    ap.add_argument("--reps", type=int, default=9)
    args = ap.parse_args(argv)
    import bench_node as bn
    import numba

    from xmetro_ros.judge.inference import ModelSet
    from xmetro_ros.judge.scan_handler import ScanHandler
    from xmetro_ros.scan.scanner import ScannerModel

    numba.set_num_threads(1)
    scanner = ScannerModel.load()
    handlers = {"shipped": ScanHandler(ModelSet.load(None, threads=1), scanner),
                "other": ScanHandler(ModelSet.load(args.other, threads=1), scanner)}
    scan = bn._sim(bn.BIG, stamp_ns=10**9)
    for h in handlers.values():  # kernels loaded, caches warm
        h.process(scan)
        h.process(scan)
    times: dict[str, list[float]] = {k: [] for k in handlers}
    for _ in range(args.reps):
        for k, h in handlers.items():
            t = time.perf_counter()
            h.process(scan)
            times[k].append(time.perf_counter() - t)
    for k, v in times.items():
        print(f"{k} ({handlers[k].model.id}): median {np.median(v) * 1e3:.1f} ms, min {min(v) * 1e3:.1f} ms")
    ratio = np.median(np.asarray(times["shipped"]) / np.asarray(times["other"]))
    print(f"paired median ratio shipped / other: {ratio:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
