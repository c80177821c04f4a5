"""Peer process for test_node_qos.py: a driver that publishes one large PointCloud2 several times on ``--topic`` with
``--reliability`` (reliable or best_effort), then reports what the node said on /diagnostics.

Run with the environment the test gives it (a user's default DDS settings: no profile file). Waits for the node's
subscription to match (and ``--settle`` seconds, for ``reliability: auto`` to adapt), publishes ``--count`` clouds of
``--bytes`` bytes one second apart, listens to /diagnostics for ``--listen`` more seconds and prints one JSON line:
``{"matched": bool, "status": {key: value of the last DiagnosticStatus}, "level": int, "message": str}``.
"""

from __future__ import annotations

import argparse
import json
import time

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2, PointField


def cloud(n_bytes: int) -> PointCloud2:
    """An unorganized x, y, z float32 cloud (point_step 16) of about ``n_bytes`` bytes, points 0.1 m away."""
    import numpy as np

    n = n_bytes // 16
    pts = np.zeros((n, 4), np.float32)
    pts[:, 0] = np.linspace(-0.01, 0.01, n, dtype=np.float32)
    pts[:, 2] = 0.1
    msg = PointCloud2(height=1, width=n, is_bigendian=False, point_step=16, row_step=16 * n, is_dense=True)
    msg.header.frame_id = "scanner"
    msg.fields = [PointField(name=c, offset=4 * i, datatype=PointField.FLOAT32, count=1) for i, c in enumerate("xyz")]
    msg.data = pts.tobytes()
    return msg


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--topic", required=True)
    ap.add_argument("--reliability", choices=("reliable", "best_effort"), default="reliable")
    ap.add_argument("--bytes", type=int, default=856_000)
    ap.add_argument("--count", type=int, default=6)
    ap.add_argument("--settle", type=float, default=3.0)
    ap.add_argument("--listen", type=float, default=4.0)
    a = ap.parse_args()
    rclpy.init()
    node = rclpy.create_node("big_cloud_peer")
    rel = ReliabilityPolicy.RELIABLE if a.reliability == "reliable" else ReliabilityPolicy.BEST_EFFORT
    pub = node.create_publisher(PointCloud2, a.topic, QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=10, reliability=rel, durability=DurabilityPolicy.VOLATILE))
    last: list[DiagnosticArray] = []
    node.create_subscription(DiagnosticArray, "/diagnostics", last.append, 10)

    def spin(seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.05)

    deadline = time.monotonic() + 30.0
    while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
        spin(0.1)
    matched = pub.get_subscription_count() > 0
    spin(a.settle)
    msg = cloud(a.bytes)
    for _ in range(a.count):
        msg.header.stamp = node.get_clock().now().to_msg()
        pub.publish(msg)
        spin(1.0)
    spin(a.listen)
    st = last[-1].status[0] if last and last[-1].status else None
    out = {"matched": matched, "status": {kv.key: kv.value for kv in st.values} if st else {},
           "level": int.from_bytes(st.level, "little") if isinstance(st.level, bytes) else int(st.level) if st else -1,
           "message": st.message if st else ""}
    print(json.dumps(out), flush=True)
    node.destroy_node()
    rclpy.shutdown()


if __name__ == "__main__":
    main()
