"""``xmetro_node``: judges laser-scanner point clouds live — per-point predicted errors, flags, verdict, services.

Topics (names relative to the node; ``~`` = the node's private namespace):

- sub ``scan`` (sensor_msgs/PointCloud2, metres; organized or not; float x, y, z required, other fields kept):
  sensor-data QoS (keep last 5, volatile) with the reliability of the ``reliability`` parameter.
- sub ``scanner_settings`` (xmetro_ros/ScannerSettings, reliable, transient-local, depth 10): each scan uses the
  latest settings stamped at or before it (last ``settings_history`` kept); none → the configured defaults
  (ScanQuality.settings_defaulted, /diagnostics WARN).
- pub ``~/deviations`` (PointCloud2: x, y, z, dx, dy, dz, dnorm, ux, uy, uz float32 metres, flags uint16; one
  point per input point, same height × width; predicted error = nominal − measured, U its expanded uncertainty
  at 95 %), ``~/corrected`` (the input cloud, same fields, with x, y, z + predicted error, residual uncertainty U;
  points without a prediction unchanged), ``~/quality`` (ScanQuality),
  ``/diagnostics`` (DiagnosticArray, every ``diagnostics_period`` and at once on a level change).
- services ``~/explain`` (Explain.srv), ``~/recommend_settings`` (RecommendSettings.srv).

Processing runs in a worker thread fed by a bounded queue (``queue_depth``; oldest dropped and counted when full),
so services and parameter changes stay responsive whatever the executor. The computation itself is
:class:`XmetroCore` (no DDS), which ``xmetro predict`` can use offline to produce the very same messages.
"""

from __future__ import annotations

import os
import threading
import time
from collections import deque
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2

from ..msg import ScannerSettings, ScanQuality
from ..srv import Explain, RecommendSettings
from . import params as node_params
from .convert import stamp_to_ns
from .core import XmetroCore
from .diagnostics import DiagnosticsState

__all__ = [
    "READY_MESSAGE",
    "XmetroNode",
    "main",
    "output_qos",
    "scan_qos",
    "settings_qos",
]

READY_MESSAGE = "xmetro_node ready"


def scan_qos(reliability: str = "reliable", depth: int = 5) -> QoSProfile:
    """Sensor-data-compatible QoS of the ``scan`` subscription."""
    rel = ReliabilityPolicy.RELIABLE if reliability == "reliable" else ReliabilityPolicy.BEST_EFFORT
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=rel,
                      durability=DurabilityPolicy.VOLATILE)


def settings_qos() -> QoSProfile:
    """QoS of the ``scanner_settings`` subscription: reliable, transient-local, keep last 10."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def output_qos(depth: int = 10) -> QoSProfile:
    """QoS of the node's publishers: reliable, volatile, keep last ``depth``."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


class XmetroNode(Node):
    """The live node (see the module docstring). Extra keyword arguments go to ``rclpy.node.Node``
    (``context``, ``parameter_overrides``, ``cli_args``...)."""

    def __init__(self, node_name: str = "xmetro_node", **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        node_params.declare_all(self)
        values = node_params.values_from_node(self)
        reason = node_params.validate(values, values)
        if reason:
            raise ValueError(f"invalid parameter: {reason}")
        self.core = XmetroCore(values, self.get_logger())
        log = self.get_logger()
        if self.core.degraded:
            log.error(f"starting DEGRADED: {self.core.degraded}; scans get ERROR MODEL_UNAVAILABLE, services fail")
        self.diag = DiagnosticsState(self.core.scanner.id, self.core.model_id, self.core.degraded)
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self._work_group = MutuallyExclusiveCallbackGroup()
        self._srv_group = ReentrantCallbackGroup()
        # Clouds: a short writer history (each 180k-point output is ~10 MB; reliable writers keep `depth` samples).
        self.pub_dev = self.create_publisher(PointCloud2, "~/deviations", output_qos(2))
        self.pub_corr = self.create_publisher(PointCloud2, "~/corrected", output_qos(2))
        self.pub_quality = self.create_publisher(ScanQuality, "~/quality", output_qos())
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", output_qos())
        self.sub_scan = self.create_subscription(PointCloud2, "scan", self._on_scan,
                                                 scan_qos(values["reliability"]), callback_group=self._work_group)
        self.sub_settings = self.create_subscription(ScannerSettings, "scanner_settings", self._on_settings,
                                                     settings_qos(), callback_group=self._work_group)
        self.srv_explain = self.create_service(Explain, "~/explain", self._on_explain,
                                               callback_group=self._srv_group)
        self.srv_recommend = self.create_service(RecommendSettings, "~/recommend_settings", self._on_recommend,
                                                 callback_group=self._srv_group)
        self._queue: deque[tuple[PointCloud2, float]] = deque()
        self._qmax = int(values["queue_depth"])
        self._cv = threading.Condition()
        self._stop = False
        self._diag_lock = threading.Lock()
        self._worker = threading.Thread(target=self._work, name="xmetro-worker", daemon=True)
        self._worker.start()
        self.timer_diag = self.create_timer(float(values["diagnostics_period"]), self._publish_diag,
                                            callback_group=self._srv_group)
        self._publish_diag()
        log.info(f"{READY_MESSAGE}: model {self.core.model_id or '(none)'}, scanner {self.core.scanner.id}, "
                 f"scan QoS {values['reliability']}")

    # ------------------------------------------------------------------ callbacks
    def _on_set_parameters(self, params: list[Any]) -> SetParametersResult:
        changes = {p.name: p.value for p in params}
        current = dict(self.core.values)
        reason = node_params.validate(changes, current)
        if reason:
            return SetParametersResult(successful=False, reason=reason)
        ours = {k: v for k, v in changes.items() if k in current}
        self.core.update_values(ours)
        if ours:
            self.get_logger().info(f"parameters changed: {ours}")
        return SetParametersResult(successful=True)

    def _on_settings(self, msg: ScannerSettings) -> None:
        err = self.core.add_settings(msg)
        if err:
            self.get_logger().error(f"invalid ScannerSettings stamped {stamp_to_ns(msg.header.stamp)} ns: {err}")

    def _on_scan(self, msg: PointCloud2) -> None:
        t0 = time.monotonic()
        self.diag.on_received()
        with self._cv:
            if len(self._queue) >= self._qmax:
                self._queue.popleft()
                self.diag.on_dropped()
                self.get_logger().warning(f"processing queue full ({self._qmax}): oldest scan dropped")
            self._queue.append((msg, t0))
            self._cv.notify()

    def _work(self) -> None:
        while True:
            with self._cv:
                while not self._queue and not self._stop:
                    self._cv.wait(0.5)
                if self._stop:
                    return
                msg, t0 = self._queue.popleft()
            try:
                self._process(msg, t0)
            except Exception as e:
                try:
                    self.get_logger().error(f"unexpected failure while publishing: {type(e).__name__}: {e}")
                except Exception:
                    return

    def _process(self, msg: PointCloud2, t0: float) -> None:
        out = self.core.judge(msg, t0)
        q = out.quality
        if out.deviations is not None:
            self.pub_dev.publish(out.deviations)
            self.pub_corr.publish(out.corrected)
        q.processing_latency = time.monotonic() - t0
        self.pub_quality.publish(q)
        if q.verdict == ScanQuality.VERDICT_ERROR:
            self.get_logger().error(out.log)
        elif q.settings_defaulted:
            self.get_logger().warning(out.log)
        else:
            self.get_logger().debug(out.log)
        before = self.diag.published_level
        self.diag.on_result(int(q.verdict), q.message, q.processing_latency, bool(q.settings_defaulted))
        if self.diag.level() != before:
            self._publish_diag()

    def _publish_diag(self) -> None:
        with self._diag_lock:
            try:
                self.pub_diag.publish(self.diag.build(self.get_clock().now().to_msg()))
            except Exception:
                pass

    def _on_explain(self, req: Explain.Request, resp: Explain.Response) -> Explain.Response:
        out = self.core.explain(req)
        if not out.success:
            self.get_logger().warning(f"~/explain refused: {out.message}")
        return out

    def _on_recommend(self, req: RecommendSettings.Request, resp: RecommendSettings.Response) -> Any:
        out = self.core.recommend(req)
        if not out.success:
            self.get_logger().warning(f"~/recommend_settings refused: {out.message}")
        return out

    def queue_length(self) -> int:
        return len(self._queue)

    def destroy_node(self) -> None:
        # Also called when __init__ failed part-way (then the worker may not exist): never mask the first error.
        if hasattr(self, "_cv"):
            with self._cv:
                self._stop = True
                self._cv.notify_all()
        if hasattr(self, "_worker"):
            self._worker.join(timeout=10.0)
        super().destroy_node()


def _limit_malloc_arenas(n: int = 2) -> None:
    """glibc: at most ``n`` malloc arenas (as MALLOC_ARENA_MAX=n) so worker threads do not grow the RSS."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").mallopt(-8, int(os.environ.get("MALLOC_ARENA_MAX", n)))  # M_ARENA_MAX = -8
    except (OSError, AttributeError, ValueError):
        pass


def main(args: list[str] | None = None) -> int:
    """Console script ``xmetro_node`` (``--ros-args --params-file config/xmetro.yaml`` etc.)."""
    from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor

    from .dds_env import apply_ros_env

    apply_ros_env()
    _limit_malloc_arenas()
    rclpy.init(args=args)
    node = None
    try:
        node = XmetroNode()
        executor = MultiThreadedExecutor(num_threads=3)
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
