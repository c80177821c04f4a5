"""Latency of a 180,000-point, 7-field PointCloud2 (5.04 MB) between two processes: our Fast DDS profile
(config/fastdds_localhost.xml: 64 MB shared-memory segment + loopback UDP) vs the Fast DDS default (profile unset:
built-in SHM with a 512 KB segment, so the cloud falls back to fragmented UDP).

For each configuration a receiver and a sender process are started with that environment (the profile is read once
per process). The sender stamps each cloud with CLOCK_MONOTONIC (system-wide) just before ``publish``; the receiver
takes the difference in its callback (so serialisation, transport and deserialisation into Python are included) and
acks it; the next cloud is sent after the ack. Configurations are interleaved in rounds so that load from other
processes on this machine hits both alike. Writes bench/results/dds.json (p50/p99/mean/min/max ms per
configuration and their ratio). Runs inside a private network namespace when root (tools/netns_run).

    python bench/bench_dds.py [--n 30] [--rounds 3]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench" / "results" / "dds.json"
N_POINTS = 180_000
FIELDS = ("x", "y", "z", "intensity", "line", "t", "u")
TOPIC, ACK = "/xm_bench/cloud", "/xm_bench/ack"


def _qos():
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


def _now_ns() -> int:
    return time.clock_gettime_ns(time.CLOCK_MONOTONIC)


def receiver(lifetime: float) -> int:
    """Ack each cloud with its one-way latency (ns) until stdin closes or ``lifetime`` s pass."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import Int64

    sys.path.insert(0, str(ROOT / "test"))
    from ros_harness import peer_stop_event

    stop = peer_stop_event(lifetime)
    ctx = rclpy.context.Context()
    rclpy.init(context=ctx)
    node = Node("bench_dds_receiver", context=ctx)
    ack = node.create_publisher(Int64, ACK, _qos())

    def on_cloud(msg: PointCloud2) -> None:
        t = _now_ns()
        ack.publish(Int64(data=t - (msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)))

    node.create_subscription(PointCloud2, TOPIC, on_cloud, _qos())
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    print("READY", flush=True)
    while not stop.is_set():
        ex.spin_once(timeout_sec=0.1)
    ex.shutdown()
    node.destroy_node()
    ctx.try_shutdown()
    return 0


def sender(n: int, warmup: int) -> int:
    """Send ``warmup + n`` clouds one at a time; print the ``n`` latencies (ns) as one JSON line."""
    import rclpy
    from builtin_interfaces.msg import Time
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import Header, Int64

    from xmetro_ros.ros.cloud import create_cloud_from_arrays

    ctx = rclpy.context.Context()
    rclpy.init(context=ctx)
    node = Node("bench_dds_sender", context=ctx)
    acks: list[int] = []
    node.create_subscription(Int64, ACK, lambda m: acks.append(m.data), _qos())
    pub = node.create_publisher(PointCloud2, TOPIC, _qos())
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    rng = np.random.default_rng(0)
    cloud = create_cloud_from_arrays(Header(frame_id="artifact"),
                                     {k: rng.normal(size=N_POINTS).astype(np.float32) for k in FIELDS},
                                     height=600, width=300)
    deadline = time.monotonic() + 60
    while (pub.get_subscription_count() < 1 or node.count_publishers(ACK) < 1) and time.monotonic() < deadline:
        ex.spin_once(timeout_sec=0.05)
    time.sleep(0.5)  # let the ack writer match our reader too
    lat: list[int] = []
    lost = 0
    for i in range(warmup + n):
        before = len(acks)
        t = _now_ns()
        cloud.header.stamp = Time(sec=t // 1_000_000_000, nanosec=t % 1_000_000_000)
        pub.publish(cloud)
        wait_until = time.monotonic() + 10
        while len(acks) == before and time.monotonic() < wait_until:
            ex.spin_once(timeout_sec=0.01)
        if len(acks) == before:
            lost += 1
        elif i >= warmup:
            lat.append(acks[-1])
        time.sleep(0.05)
    print(json.dumps({"latency_ns": lat, "lost": lost}), flush=True)
    ex.shutdown()
    node.destroy_node()
    ctx.try_shutdown()
    return 0


def _env(config: str, domain: int) -> dict[str, str]:
    from xmetro_ros.ros.dds_env import ros_env

    env = ros_env(domain)
    if config == "default":
        env.pop("FASTRTPS_DEFAULT_PROFILES_FILE", None)
        env.pop("FASTDDS_DEFAULT_PROFILES_FILE", None)
    return env


def run_config(config: str, n: int, domain: int) -> dict:
    env = _env(config, domain)
    script = str(Path(__file__).resolve())
    rx = subprocess.Popen([sys.executable, script, "--role", "receiver"], env=env, stdin=subprocess.PIPE,
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        seen = []
        for line in rx.stdout:  # skip rmw warnings until READY
            if line.strip() == "READY":
                break
            seen.append(line)
        else:
            raise RuntimeError(f"receiver failed: {''.join(seen)}")
        out = subprocess.run([sys.executable, script, "--role", "sender", "--n", str(n)], env=env,
                             capture_output=True, text=True, timeout=600)
        rows = [ln for ln in out.stdout.splitlines() if ln.startswith("{")]
        if out.returncode or not rows:
            raise RuntimeError(f"sender failed ({out.returncode}): {out.stdout}\n{out.stderr}")
        return json.loads(rows[-1])
    finally:
        rx.stdin.close()
        try:
            rx.wait(20)
        except subprocess.TimeoutExpired:
            rx.kill()
            rx.wait()


def conversion_timings(repeats: int = 20) -> dict:
    """In-process cost of packing / reading the 180k×7 cloud (median µs) and whether the reads are views."""
    from std_msgs.msg import Header

    from xmetro_ros.ros.cloud import create_cloud_from_arrays, read_points, validate_cloud, xyz_fields

    rng = np.random.default_rng(0)
    arrays = {k: rng.normal(size=N_POINTS).astype(np.float32) for k in FIELDS}

    def med(f) -> float:
        ts = []
        for _ in range(repeats):
            t = time.perf_counter()
            f()
            ts.append(time.perf_counter() - t)
        return float(np.median(ts) * 1e6)

    cloud = create_cloud_from_arrays(Header(), arrays, height=600, width=300)
    buf = np.frombuffer(cloud.data, dtype=np.uint8)
    xyz, extra = xyz_fields(cloud, ["u", "intensity"])
    return {
        "create_cloud_from_arrays_us": med(lambda: create_cloud_from_arrays(Header(), arrays, height=600, width=300)),
        "xyz_fields_xyz_u_intensity_us": med(lambda: xyz_fields(cloud, ["u", "intensity"])),
        "read_points_us": med(lambda: read_points(cloud)),
        "validate_cloud_us": med(lambda: validate_cloud(cloud)),
        "xyz_is_view": bool(np.shares_memory(xyz, buf)),
        "extra_fields_are_views": bool(all(np.shares_memory(a, buf) for a in extra.values())),
        "read_points_is_view": bool(np.shares_memory(read_points(cloud), buf)),
    }


def _stats(ns: list[int]) -> dict:
    ms = np.asarray(ns, dtype=float) / 1e6
    return {"n": int(ms.size), "p50_ms": float(np.percentile(ms, 50)), "p99_ms": float(np.percentile(ms, 99)),
            "mean_ms": float(ms.mean()), "min_ms": float(ms.min()), "max_ms": float(ms.max())}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--role", choices=("main", "sender", "receiver"), default="main")
    ap.add_argument("--n", type=int, default=30, help="measured clouds per configuration (split over rounds)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    if args.role == "receiver":
        return receiver(lifetime=600)
    if args.role == "sender":
        return sender(args.n, warmup=3)
    if "XMETRO_IN_NETNS" not in os.environ and os.geteuid() == 0:
        runner = str(ROOT / "tools" / "netns_run")
        os.execv(runner, [runner, sys.executable, str(Path(__file__).resolve()), *(argv or sys.argv[1:])])
    conversions = conversion_timings()
    configs = ("shm_profile", "default")
    per_round = max(1, args.n // args.rounds)
    lat: dict[str, list[int]] = {c: [] for c in configs}
    lost = {c: 0 for c in configs}
    base = 1 + os.getpid() % 90
    t0 = time.monotonic()
    for r in range(args.rounds):
        for k, c in enumerate(configs):
            res = run_config(c, per_round, domain=base + 2 * r + k)
            lat[c] += res["latency_ns"]
            lost[c] += res["lost"]
            print(f"round {r + 1} {c}: p50 {np.median(res['latency_ns']) / 1e6:.1f} ms", flush=True)
    stats = {c: {**_stats(lat[c]), "lost": lost[c]} for c in configs}
    result = {
        "bench": "dds",
        "what": "one-way latency of a PointCloud2 between two processes (publish → subscriber callback, rclpy)",
        "cloud": {"points": N_POINTS, "fields": list(FIELDS), "bytes": N_POINTS * 4 * len(FIELDS),
                  "height": 600, "width": 300},
        "configs": {
            "shm_profile": {**stats["shm_profile"], "profile": "config/fastdds_localhost.xml (SHM 64 MB + UDP lo)"},
            "default": {**stats["default"], "profile": "unset (Fast DDS defaults: SHM 512 KB segment + UDPv4)"},
        },
        "ratio_p50_default_over_shm": stats["default"]["p50_ms"] / stats["shm_profile"]["p50_ms"],
        "ratio_p99_default_over_shm": stats["default"]["p99_ms"] / stats["shm_profile"]["p99_ms"],
        "conversions": conversions,
        "rounds": args.rounds,
        "netns": os.environ.get("XMETRO_IN_NETNS") == "1",
        "host": {"cpus": os.cpu_count(), "loadavg_1m": os.getloadavg()[0], "python": platform.python_version(),
                 "machine": platform.machine()},
        "wall_s": time.monotonic() - t0,
        "date": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({c: {k: round(v, 2) for k, v in stats[c].items()} for c in configs}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
