"""Peer process for test_dds.py (and usable by hand): echoes our messages and serves test versions of our services.

Run as ``python test/dds_peer.py [--ns NS] [--lifetime S]`` with ``xmetro_ros.ros.dds_env.ros_env()`` as environment.
Under namespace NS (default ``/xm_peer``):

- echo: ``settings_in`` → ``settings_out`` (ScannerSettings), ``quality_in`` → ``quality_out`` (ScanQuality),
  ``cloud_in`` → ``cloud_out`` (PointCloud2, the received message republished unchanged). Inputs reliable volatile;
  outputs reliable transient local (depth 1), so a reply is never lost to a late match.
- latched: ``settings_latched`` (ScannerSettings) and ``quality_latched`` (ScanQuality) published once at start-up,
  transient local: a subscriber created later (late joiner) still gets them (see :func:`latched_settings`).
- services ``explain`` (xmetro_ros/Explain) and ``recommend_settings`` (xmetro_ros/RecommendSettings): small
  deterministic servers (see :func:`explain_response`, :func:`recommend_response`) the test checks answers against.

Prints ``READY`` once everything exists; exits when stdin closes or after ``--lifetime`` seconds.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import rclpy
from geometry_msgs.msg import Quaternion
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from ros_harness import peer_stop_event, qos
from sensor_msgs.msg import PointCloud2

from xmetro_ros.msg import ScannerSettings, ScanQuality, SettingsCandidate
from xmetro_ros.ros.convert import ns_to_stamp, settings_to_msg
from xmetro_ros.ros.rclpy_util import new_context
from xmetro_ros.scan.geometry import HeadPose
from xmetro_ros.scan.scanner import ScanSettings
from xmetro_ros.srv import Explain, RecommendSettings

FEATURES = ("lateral_density", "Inc", "R_y")
UNITS = ("1/mm", "deg", "mm")
AXES = ("x", "y", "z")


def latched_settings() -> ScannerSettings:
    """The ScannerSettings the peer latches at start-up."""
    return settings_to_msg(ScanSettings(15.0, 3.0, 2.0), HeadPose.looking_down(90.0, y_mm=-40.0), "artifact",
                           1_700_000_000_000_000_123, "xm-ls90")


def latched_quality() -> ScanQuality:
    """The ScanQuality the peer latches at start-up."""
    q = ScanQuality(model_id="peer-model", verdict=ScanQuality.VERDICT_WARN, error_code=ScanQuality.ERROR_NONE,
                    message="latched", points_received=180_000, points_valid=170_000, points_flagged=1234)
    q.header.frame_id = "artifact"
    q.header.stamp = ns_to_stamp(1_700_000_000_000_000_123)
    q.flag_names = ["OUTLIER", "GRAZING_INCIDENCE"]
    q.flag_counts = [34, 1200]
    q.mean_abs_error = [1e-5, 2e-5, 3e-5]
    q.p95_abs_error = [4e-5, 5e-5, 6e-5]
    q.usable_fraction = 0.99
    q.settings = latched_settings()
    return q


def explain_response(req: Explain.Request) -> Explain.Response:
    """SHAP-like answer: shap[p, f, a] = 1e-6 · (index_p + 1) · (f + 1) · (axis_a + 1); base 1e-5 · (axis + 1)."""
    axes = [i for i in range(3) if req.axes == 0 or req.axes & (1 << i)]
    idx = np.asarray(req.indices, dtype=np.int64)
    if len(idx) == 0:
        idx = np.arange(min(req.max_points or 10, 10))
    shap = 1e-6 * (idx[:, None, None] + 1) * (np.arange(len(FEATURES))[None, :, None] + 1) * (
        np.asarray(axes)[None, None, :] + 1)
    base = 1e-5 * (np.asarray(axes, dtype=float) + 1)
    res = Explain.Response(success=True, message="peer", model_id="peer-model")
    res.feature_names = list(FEATURES)
    res.feature_units = list(UNITS)
    res.axis_names = [AXES[a] for a in axes]
    res.base_values = base.tolist()
    res.point_indices = idx.astype(np.uint32).tolist()
    res.shap_values = shap.reshape(-1).tolist()
    res.feature_values = np.tile(np.arange(len(FEATURES), dtype=float), len(idx)).tolist()
    res.predictions = (base[None, :] + shap.sum(axis=1)).reshape(-1).tolist()
    res.mean_abs_shap = np.abs(shap).mean(axis=0).reshape(-1).tolist()
    return res


def recommend_response(req: RecommendSettings.Request) -> RecommendSettings.Response:
    """Ranks the candidates by ``score = 1e-5 / lateral_density[per mm]`` (denser is better); best first."""
    cands = list(req.candidates) or [latched_settings()]
    scores = [1e-5 / (c.lateral_density * 1e-3) for c in cands]
    order = np.argsort(scores, kind="stable")
    res = RecommendSettings.Response(success=True, message="peer", model_id="peer-model")
    res.recommended_settings = cands[order[0]]
    res.recommended_orientation = Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)
    res.mean_abs_error_before = 2e-5
    res.p95_abs_error_before = 5e-5
    res.mean_abs_error_after = scores[order[0]]
    res.p95_abs_error_after = 2 * scores[order[0]]
    res.coverage_before, res.coverage_after = 0.8, 0.9
    res.meets_tolerance = req.tolerance > 0 and res.p95_abs_error_after <= req.tolerance
    res.alternatives = [
        SettingsCandidate(settings=cands[i], orientation=res.recommended_orientation, mean_abs_error=scores[i],
                          p95_abs_error=2 * scores[i], coverage=0.9, score=scores[i])
        for i in order
    ]
    return res


class Peer(Node):
    def __init__(self, context: rclpy.context.Context, ns: str) -> None:
        super().__init__("dds_peer", namespace=ns, context=context)
        self._keep = []
        for msg_type, name in ((ScannerSettings, "settings"), (ScanQuality, "quality"), (PointCloud2, "cloud")):
            pub = self.create_publisher(msg_type, f"{name}_out", qos(1, latched=True))
            self._keep.append(self.create_subscription(msg_type, f"{name}_in", pub.publish, qos(2)))
            self._keep.append(pub)
        self.latched_settings = self.create_publisher(ScannerSettings, "settings_latched", qos(1, latched=True))
        self.latched_quality = self.create_publisher(ScanQuality, "quality_latched", qos(1, latched=True))
        self.latched_settings.publish(latched_settings())
        self.latched_quality.publish(latched_quality())
        self.create_service(Explain, "explain", lambda req, res: explain_response(req))
        self.create_service(RecommendSettings, "recommend_settings", lambda req, res: recommend_response(req))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ns", default="/xm_peer")
    ap.add_argument("--lifetime", type=float, default=180.0)
    args = ap.parse_args(argv)
    stop = peer_stop_event(args.lifetime)
    ctx = new_context()
    node = Peer(ctx, args.ns)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    print("READY", flush=True)
    while not stop.is_set():
        executor.spin_once(timeout_sec=0.1)
    executor.shutdown()
    node.destroy_node()
    ctx.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
