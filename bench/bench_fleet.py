"""`xmetro fleet predict` throughput with 1 and 2 Dask workers, and peak memory per worker → bench/results/fleet.json.

Inputs: ``--bags`` copies of bags/demo.mcap (4 scans of 31k-84k points each, settings before each scan), judged by
the shipped default model with ``threads=1`` (one core per worker process). In one run, one after the
other: a local cluster of 1 worker process, then of 2, each over the same bags into a fresh output directory
(``--deterministic``; cluster start-up timed apart); throughput = scans / wall time from submission to the last
bag's completion; scaling ratio = throughput(2) / throughput(1) (ideal: 2 on an idle 2-core machine; this machine
is shared, so the load average before each run is recorded, and the workers' CPU and wall seconds per scan: equal
CPU per scan with more wall per scan means the workers waited for a core). Every output bag is checked identical to
the 1-worker one.

Memory: a "large" bag (``--repeat`` times demo's messages, log times shifted) and a small one (demo) are judged on
a fresh 1-worker cluster; each worker's peak RSS after the small bag and after the large bag: streaming (message
by message, outputs not kept) keeps the peak independent of the bag's length.

Run: ``python bench/bench_fleet.py [--bags 8] [--repeat 10]``.
"""

from __future__ import annotations

import argparse
import filecmp
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

DEMO = ROOT / "bags" / "demo.mcap"
PARAMS = {"threads": "1"}


def make_large_bag(path: Path, repeat: int) -> int:
    """``repeat`` copies of demo's messages (raw CDR), each copy's log times shifted after the previous one."""
    from xmetro_ros.bag.reader import BagReader
    from xmetro_ros.bag.writer import BagWriter

    r = BagReader(DEMO)
    msgs = list(r.messages(deserialize=False))
    span = msgs[-1].log_time_ns - msgs[0].log_time_ns + 1_000_000_000
    with BagWriter(path, compression="zstd") as w:
        for t, ty in r.topics().items():
            w.add_topic(t, ty)
        for k in range(repeat):
            for m in msgs:
                w.write(m.topic, m.raw, m.log_time_ns + k * span)
    return sum(1 for m in msgs if m.topic == "/scan") * repeat


def run_fleet(inputs: list[Path], out: Path, workers: int) -> dict:
    from xmetro_ros.apps import fleet

    jobs = fleet.plan_jobs(inputs, out)
    load = os.getloadavg()[0]
    t0 = time.monotonic()
    with fleet.dask_client(workers=workers) as client:
        t_up = time.monotonic() - t0
        t1 = time.monotonic()
        res = fleet.run_fleet(jobs, client, out, params=PARAMS, deterministic=True)
        wall = time.monotonic() - t1
    bad = [b for b in res.bags if b["status"] != "done"]
    if bad:
        raise RuntimeError(f"bags not done: {bad}")
    return {"workers": workers, "bags": len(jobs), "scans": res.scans, "wall_s": round(wall, 2),
            "scans_per_s": round(res.scans / wall, 3), "cluster_start_s": round(t_up, 2),
            "loadavg_1min_before": round(load, 2),
            "worker_cpu_s_per_scan": round(sum(b["cpu_s"] for b in res.bags) / res.scans, 3),
            "worker_wall_s_per_scan": round(sum(b["wall_s"] for b in res.bags) / res.scans, 3),
            "peak_rss_mb_per_worker": sorted(round(max(b["peak_rss_mb"] for b in res.bags if b["worker_pid"] == p))
                                             for p in {b["worker_pid"] for b in res.bags})}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--bags", type=int, default=8)
    ap.add_argument("--repeat", type=int, default=10)
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "fleet.json"))
    args = ap.parse_args()
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

    from xmetro_ros.apps import fleet

    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        inp = d / "in"
        inp.mkdir()
        bags = []
        for i in range(args.bags):
            shutil.copy(DEMO, inp / f"bag{i:02d}.mcap")
            bags.append(inp / f"bag{i:02d}.mcap")
        runs = [run_fleet(bags, d / f"out{w}", w) for w in (1, 2)]
        identical = all(filecmp.cmp(d / "out1" / b.name, d / "out2" / b.name, shallow=False) for b in bags)

        large = d / "large" / "large.mcap"
        large.parent.mkdir()
        n_large = make_large_bag(large, args.repeat)
        small_jobs = fleet.plan_jobs([DEMO], d / "mem_small")
        large_jobs = fleet.plan_jobs([large], d / "mem_large")
        with fleet.dask_client(workers=1) as client:
            r_small = fleet.run_fleet(small_jobs, client, d / "mem_small", params=PARAMS).bags[0]
            r_large = fleet.run_fleet(large_jobs, client, d / "mem_large", params=PARAMS).bags[0]
        out_large = Path(large_jobs[0].out)
        memory = {
            "small_bag": {"scans": r_small["scans"], "input_mb": round(DEMO.stat().st_size / 1e6, 1),
                          "worker_peak_rss_mb": round(r_small["peak_rss_mb"])},
            "large_bag": {"scans": r_large["scans"], "input_mb": round(large.stat().st_size / 1e6, 1),
                          "output_mb": round(out_large.stat().st_size / 1e6, 1),
                          "worker_peak_rss_mb": round(r_large["peak_rss_mb"])},
        }
        assert r_large["scans"] == n_large

    result = {
        "bench": "fleet",
        "what": "xmetro fleet predict on local Dask clusters of 1 and 2 worker processes (same run), "
                f"{args.bags} copies of bags/demo.mcap, default model, threads=1, --deterministic",
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                    "note": "2 cores shared with other engineers' jobs: noisy; see loadavg_1min_before"},
        "runs": runs,
        "scaling_ratio_2_over_1": round(runs[1]["scans_per_s"] / runs[0]["scans_per_s"], 3),
        "outputs_identical_1_vs_2_workers": identical,
        "memory": memory,
        "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result, indent=1))
    return 0 if identical else 1


if __name__ == "__main__":
    sys.exit(main())
