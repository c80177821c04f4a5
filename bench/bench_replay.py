"""Replay throughput into a consumer → bench/results/replay.json.

A synthetic bag (N scans of P points: x, y, z, intensity float32, with a ScannerSettings before each) is replayed
by ``xmetro_ros.apps.replay.replay_bag`` into a minimal consumer node standing in for xmetro_node: it answers each scan
with a ScanQuality (header copied) on ``/xmetro_node/quality`` and does no processing, so the numbers are those of
the replay machinery itself (bag reading, DDS publishing, settings acknowledgement, quality handshake):

- ``fast``: each scan waits for the previous scan's quality (the no-drop mode); steady-state scans/s and MB/s
  measured from the first answer to the last;
- ``rate``: original timing scaled by 1000 (no handshake; the consumer's queue may drop — counted);
- with one settings message at the start, and with one before every scan (each settings message is acknowledged
  and given 0.1 s to reach the node's executor before the next scan: that wait dominates).

Run: ``python bench/bench_replay.py [--scans 30] [--points 100000]`` (inside tools/netns_run when root).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from xmetro_ros.ros.dds_env import apply_ros_env  # noqa: E402


def make_bag(path: Path, n_scans: int, n_points: int, settings_every_scan: bool, seed: int = 0) -> int:
    from std_msgs.msg import Header

    from xmetro_ros.bag import qos_profiles
    from xmetro_ros.bag.writer import BagWriter
    from xmetro_ros.ros.cloud import create_cloud_from_arrays
    from xmetro_ros.ros.convert import ns_to_stamp, settings_to_msg
    from xmetro_ros.scan.geometry import HeadPose
    from xmetro_ros.scan.scanner import ScanSettings

    rng = np.random.default_rng(seed)
    t0 = 1_735_689_600_000_000_000
    with BagWriter(path) as w:
        w.add_topic("/scan", "sensor_msgs/msg/PointCloud2", [qos_profiles.CLOUD])
        w.add_topic("/scanner_settings", "xmetro_ros/msg/ScannerSettings", [qos_profiles.SETTINGS])
        for i in range(n_scans):
            stamp = t0 + i * 100_000_000
            s = settings_to_msg(ScanSettings(10.0, 4.0, 0.5), HeadPose.looking_down(90.0), "artifact", stamp - 1000,
                                "xm-ls90")
            if settings_every_scan or i == 0:
                w.write("/scanner_settings", s, stamp - 1000)
            pts = rng.normal(size=(n_points, 3)).astype(np.float32) * 0.02
            arrays = {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2],
                      "intensity": rng.random(n_points).astype(np.float32)}
            w.write("/scan", create_cloud_from_arrays(Header(stamp=ns_to_stamp(stamp), frame_id="artifact"), arrays),
                    stamp)
    return path.stat().st_size


def consumer_factory(ctx):
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    from xmetro_ros.msg import ScannerSettings, ScanQuality

    node = Node("xmetro_node", context=ctx)
    qos = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
    pub = node.create_publisher(ScanQuality, "~/quality", QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
    node.received = 0

    def on_scan(msg: PointCloud2) -> None:
        node.received += 1
        q = ScanQuality()
        q.header = msg.header
        q.points_received = msg.width * msg.height
        pub.publish(q)

    node.create_subscription(ScannerSettings, "scanner_settings", lambda m: None, qos)
    # Like xmetro_node: /diagnostics periodically (the replay takes its first one as proof of matching).
    diag = node.create_publisher(DiagnosticArray, "/diagnostics", QoSProfile(depth=10,
                                 reliability=ReliabilityPolicy.RELIABLE))
    node.create_timer(0.2, lambda: diag.publish(DiagnosticArray()))
    node.create_subscription(PointCloud2, "scan", on_scan, qos)
    return node


def rosbags_read(bag: Path, payload_bytes: int, repeats: int = 3) -> dict:
    """rosbags (an independent reader) reading and deserializing every message of the same bag, best of
    ``repeats``: the ceiling a replay could reach if publishing cost nothing."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_KILTED)
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        with AnyReader([bag], default_typestore=store) as ar:
            for c, _t, raw in ar.messages():
                ar.deserialize(raw, c.msgtype)
        best = min(best, time.perf_counter() - t)
    return {"seconds": round(best, 3), "MB_per_s": round(payload_bytes / best / 1e6, 1)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scans", type=int, default=30)
    ap.add_argument("--points", type=int, default=100_000)
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "replay.json")
    args = ap.parse_args(argv)
    apply_ros_env()
    from xmetro_ros.apps.replay import replay_bag
    from xmetro_ros.ros.rclpy_util import NodeSpinner

    machine = {"python": platform.python_version(), "cpus": os.cpu_count(), "platform": platform.platform()}
    results = {"machine": machine,
               "scans": args.scans, "points_per_scan": args.points, "runs": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for every in (False, True):
            bag = Path(tmp) / f"bench_{every}.mcap"
            size = make_bag(bag, args.scans, args.points, settings_every_scan=every)
            key = "settings_every_scan" if every else "settings_once"
            results[f"bag_bytes_{key}"] = size
            modes = (("fast", {"fast": True}), ("rate", {"rate": 1000.0})) if not every else (("fast", {"fast": True}),)
            for mode, kw in modes:
                stamps: list[float] = []
                with NodeSpinner(consumer_factory) as sp:
                    res = replay_bag(bag, discovery_timeout=30.0, answer_timeout=30.0,
                                     log=lambda s, stamps=stamps: s.startswith("#") and stamps.append(time.monotonic()),
                                     **kw)
                    received = sp.node.received
                run = {
                    "wall_s_incl_discovery": round(res.wall_s, 3),
                    "scans_sent": res.scans_sent,
                    "scans_received_by_consumer": received,
                    "qualities_received": res.answered,
                    "bytes_sent": res.bytes_sent,
                }
                # Steady state: from the first answered scan to the last (discovery and set-up excluded).
                if mode == "fast" and len(stamps) >= 2:
                    dt = stamps[-1] - stamps[0]
                    n = len(stamps) - 1
                    run.update(scans_per_s=round(n / dt, 2), ms_per_scan=round(dt / n * 1e3, 2),
                               MB_per_s=round(res.bytes_sent / args.scans * n / dt / 1e6, 2))
                results["runs"][f"{mode}_{key}"] = run
                print(f"{mode} ({key}): {json.dumps(run)}")
            if not every:
                results["rosbags_read_same_bag"] = rosbags_read(bag, res.bytes_sent)
                fast = results["runs"]["fast_settings_once"]
                if "MB_per_s" in fast:
                    results["rosbags_read_same_bag"]["replay_fast_over_rosbags_read"] = round(
                        fast["MB_per_s"] / results["rosbags_read_same_bag"]["MB_per_s"], 3)
                print(f"rosbags read of the same bag: {json.dumps(results['rosbags_read_same_bag'])}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
