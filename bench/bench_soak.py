"""Memory soak of a real ``xmetro_node`` process: repeated cycles of good and bad inputs, big clouds included;
writes bench/results/soak.json.

Each cycle sends, one after the other (each waiting for its ScanQuality): a small good scan (~16k valid points), a
big good scan (~180k valid points, 371k cells), an oversize cloud (2 big scans side by side: TOO_MANY_POINTS), a
scan with 3e38 m on a third of its points (OUT_OF_VOLUME flags), the malformed / hostile catalogue of
``test/test_node_helpers.bad_inputs`` (issue 12's stall input included: a field claiming count 1,000,000, rejected
BAD_LAYOUT by cloud.py's O(fields) layout check), then a burst of 10 small scans (queue drops, losses before the
callback). The node's resident set size is sampled every 0.5 s. Goal: flat after warm-up — growth < 5 % between the
median of the second quarter of the run and the median of the last quarter. Also checked: every scan accounted for
(received + lost = sent; received = judged + dropped) and no published point with NaN deviation and flags 0. Also
measured, in this process: the time ``cloud.validate_cloud`` takes to reject the stall input (median of 2,000 calls;
``stall_input_rejection_us``).

    python bench/bench_soak.py [--duration 180] [--model DIR]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "2")
os.environ.setdefault("MALLOC_ARENA_MAX", "2")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from collections import Counter  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "test"))  # the bad-input catalogue and the output invariant of the node tests
OUT = ROOT / "bench" / "results" / "soak.json"


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def _stall_rejection_us(bad_inputs, calls: int = 2000) -> dict[str, float]:
    """Issue 12's stall input (the catalogue's last cloud) rejected by ``validate_cloud``: median and max of
    ``calls`` timed calls, microseconds (the check ``XmetroCore.judge`` makes before decoding a cloud)."""
    from xmetro_ros.ros.cloud import CloudFormatError, validate_cloud

    name, msg, _ = bad_inputs(lambda: 0)[-1]
    assert name == "field count 1,000,000", name
    times = []
    for _ in range(calls):
        t = time.perf_counter()
        try:
            validate_cloud(msg, require_valid_points=True)
        except CloudFormatError as e:
            assert e.code == "BAD_LAYOUT", e
        else:
            raise AssertionError("the stall input was accepted")
        times.append(time.perf_counter() - t)
    return {"median": round(float(np.median(times)) * 1e6, 2), "max": round(float(np.max(times)) * 1e6, 2),
            "calls": calls}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=180.0, help="seconds of cycles (default 180)")
    ap.add_argument("--model", default="", help="model set directory (default: the shipped model)")
    args = ap.parse_args(argv)

    from rclpy.node import Node
    from test_node_helpers import (
        NodeClient,
        absurd_scan,
        assert_points_accounted,
        bad_inputs,
        cloud_of,
        settings_msg,
        sim_scan,
    )

    from xmetro_ros.ros.convert import ns_to_stamp
    from xmetro_ros.ros.dds_env import fresh_domain_id
    from xmetro_ros.ros.rclpy_util import NodeProcess, NodeSpinner, wait_for
    from xmetro_ros.scan.artifacts import Sphere
    from xmetro_ros.scan.scanner import ScanSettings
    from xmetro_ros.sim import simulate_scan

    S = 1_000_000_000
    domain = fresh_domain_id()
    # reliable: the soak counts an answer for every scan it sends (a best-effort subscription may lose a 20 MB cloud)
    params = {"max_points": 400_000, "max_processing_time": 5.0, "reliability": "reliable"}
    if args.model:
        params["model_dir"] = args.model
    proc = NodeProcess(params_file=str(ROOT / "config" / "xmetro.yaml"), params=params, domain_id=domain)
    proc.start(timeout=120.0)
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    cli = NodeSpinner(lambda ctx: Node("xmetro_soak", context=ctx))
    samples: list[tuple[float, float]] = []
    stop = threading.Event()

    def sample() -> None:
        while not stop.wait(0.5):
            try:
                samples.append((time.monotonic(), _rss_mb(proc.pid)))
            except OSError:
                return

    sampler = threading.Thread(target=sample, daemon=True)
    t = [100 * S]

    def stamp() -> int:
        t[0] += 1000
        return t[0]

    codes: Counter[int] = Counter()
    sent = 0
    cycles = 0
    checked = 0
    try:
        client = NodeClient(cli.node)
        client.wait_matched()
        client.pub_settings.publish(settings_msg(sim_scan(0), 99 * S))
        small = cloud_of(sim_scan(0))
        big = cloud_of(simulate_scan(Sphere(27.5, np.zeros(3)), ScanSettings(16.0, 5.0, 0.5), seed=0))
        rows = np.frombuffer(bytes(big.data), np.uint8).reshape(big.height, -1)
        over = cloud_of(simulate_scan(Sphere(27.5, np.zeros(3)), ScanSettings(16.0, 5.0, 0.5), seed=0))
        over.width *= 2
        over.row_step = over.width * over.point_step
        over.data = np.concatenate([rows, rows], axis=1).tobytes()
        absurd = cloud_of(absurd_scan(0))
        assert wait_for(lambda: client.node.count_publishers("/xmetro_node/quality") > 0, 30.0)

        def send(msg) -> None:
            nonlocal sent, checked
            msg.header.stamp = ns_to_stamp(stamp())
            q, dev, _ = client.send(msg)
            sent += 1
            codes[int(q.error_code)] += 1
            if dev is not None:
                assert_points_accounted(dev)
                checked += 1
            with client.lock:  # keep the client's own memory flat: drop what was checked
                client.quality.clear()
                client.deviations.clear()
                client.corrected.clear()
                client.diagnostics.clear()
                client.logs.clear()

        send(small)  # settings in place and a baseline sequence number
        sampler.start()
        t_start = time.monotonic()
        while time.monotonic() - t_start < args.duration:
            for msg in (small, big, over, absurd):
                send(msg)
            for _name, msg, _codes in bad_inputs(stamp):
                send(msg)
            for _ in range(10):
                small.header.stamp = ns_to_stamp(stamp())
                client.pub_scan.publish(small)
                sent += 1
            send(small)
            cycles += 1
        # the accounting of the last answer covers everything sent before it
        small.header.stamp = ns_to_stamp(stamp())
        q, _, _ = client.send(small)
        sent += 1
        stop.set()
        sampler.join(5.0)
    finally:
        stop.set()
        cli.close()
        code = proc.stop()

    stall_us = _stall_rejection_us(bad_inputs)
    rss = np.array([r for _, r in samples])
    n = len(rss)
    q2, q4 = rss[n // 4: n // 2], rss[3 * n // 4:]
    growth = (np.median(q4) - np.median(q2)) / np.median(q2) * 100.0
    accounted = int(q.scans_received) + int(q.scans_lost)
    result = {
        "machine": platform.node(), "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "duration_s": round(samples[-1][0] - samples[0][0], 1) if samples else 0.0,
        "cycles": cycles, "scans_sent": sent,
        "answers_by_error_code": {str(k): v for k, v in sorted(codes.items())},
        "accounting": {"scans_received": int(q.scans_received), "scans_judged": int(q.scans_judged),
                       "scans_dropped": int(q.scans_dropped), "scans_lost": int(q.scans_lost),
                       "received_plus_lost_equals_sent": accounted == sent,
                       "received_equals_judged_plus_dropped": int(q.scans_received) == int(q.scans_judged)
                       + int(q.scans_dropped)},
        "deviation_clouds_checked_no_silent_nan": checked,
        "rss_samples": n,
        "rss_after_warmup_mb": round(float(rss[n // 4]), 1),
        "rss_q2_median_mb": round(float(np.median(q2)), 1),
        "rss_q4_median_mb": round(float(np.median(q4)), 1),
        "rss_max_mb": round(float(rss.max()), 1),
        "rss_quarter_medians_mb": [round(float(np.median(rss[k * n // 4:(k + 1) * n // 4])), 1) for k in range(4)],
        "rss_tenth_medians_mb": [round(float(np.median(rss[k * n // 10:(k + 1) * n // 10])), 1) for k in range(10)],
        "rss_growth_q2_to_q4_pct": round(float(growth), 2),
        "goal_growth_pct": 5.0,
        "node_exit_code": code,
        "stall_input_rejection_us": stall_us,
    }
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result, indent=1))
    ok = result["accounting"]["received_plus_lost_equals_sent"] and result["accounting"][
        "received_equals_judged_plus_dropped"]
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
