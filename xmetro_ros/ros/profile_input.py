"""The node's profile-stream input (parameter ``profile_input``; docs/profile-streams.md): the wiring only.

Subscriptions: ``profiles`` (``sensor_msgs/PointCloud2``, one laser-line profile per message in the sensor frame, as
line-scanner drivers publish; best effort unless ``reliability`` is reliable, depth 200 for 1 kHz bursts), ``/tf``
and ``/tf_static`` (``tf2_msgs/TFMessage``, QoS as tf2_ros's listener: reliable, depth 100, the static one
transient-local). These three and the stream's timer live on a helper node ``<node>_profile_input`` with a
single-threaded executor of its own (remap ``profiles`` with a rule for every node, or for that one). On the node
itself: ``scan_active`` (``std_msgs/Bool``: true starts a scan, false ends it; ``scan_trigger: signal``), services
``~/start_scan`` and ``~/stop_scan`` (``std_srvs/Trigger``, the same). The timer (every :data:`POLL_PERIOD_S`)
poses the profiles received since its last run together and advances the stream's clock, so that tf timeouts and
gaps end without a new profile.

Everything else is :class:`~xmetro_ros.ros.profile_stream.ProfileStream` (assembly, drop reports, accounting) and
:meth:`~xmetro_ros.ros.core.XmetroCore.posed_input` (settings, cloud): an assembled scan joins the node's one
processing queue like a scan from ``scan``. Drops are published as ERROR ScanQuality with their own code, logged,
and on /diagnostics (WARN for ``loss_warn_period``, the accounting as values).
"""

from __future__ import annotations

import threading
import time
import traceback
from collections.abc import Callable
from typing import Any

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.executors import ExternalShutdownException, ShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Bool
from std_srvs.srv import Trigger

from ..scan.assembly import AssembledScan
from .posed_scans import PosedScan
from .profile_stream import ProfileStream, StreamError, error_quality, scan_header, stream_from_values
from .rclpy_util import NodeMixin, SequenceGaps

__all__ = ["POLL_PERIOD_S", "ProfileInput", "tf_qos"]

#: Period of the timer that poses the profiles received since its last run and advances the stream's clock, s.
POLL_PERIOD_S = 0.02


def tf_qos(static: bool) -> QoSProfile:
    """tf2_ros's listener QoS: reliable, keep last 100; transient-local for /tf_static (latched by broadcasters)."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if static else DurabilityPolicy.VOLATILE)


class ProfileInput(NodeMixin):
    """Profile + tf subscriptions feeding a :class:`ProfileStream`, mixed into the node's wiring."""

    core: Any
    diag: Any
    _inputs: list[Any]
    # the node's processing queue and ScanQuality publisher (ScanWorker, mixed in beside this class)
    _enqueue: Callable[..., None]
    _publish_quality: Callable[[Any], None]

    def _create_profile_inputs(self, values: dict[str, Any]) -> None:
        """Create the profile stream's entities (``values``: the node's parameter values)."""
        from tf2_msgs.msg import TFMessage  # built from its definition by setup.py where no tf2_msgs is installed

        self.stream: ProfileStream | None = stream_from_values(values)
        # fed from the profile, tf, signal and timer callbacks; re-entered when the queue drops a scan (_posed_done)
        self._stream_lock = threading.RLock()
        self._driver_values: dict[str, float] | None = None
        self._incoming: list[PointCloud2] = []
        self._profile_gaps = SequenceGaps()
        reliable = values["reliability"] == "reliable"
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=200,
                         reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                         durability=DurabilityPolicy.VOLATILE)
        # The stream's subscriptions and timer live on a helper node spun by a single-threaded executor of its own:
        # on rclpy's multi-threaded executor (the node's) most of a 300 Hz driver's profiles were lost before their
        # callback; a single-threaded one takes a 1 kHz stream whole (bench/bench_profiles.py).
        self.stream_node = Node(f"{self.get_name()}_profile_input", namespace=self.get_namespace(),
                                context=self.context, start_parameter_services=False)
        sn = self.stream_node
        self.sub_profiles = sn.create_subscription(PointCloud2, "profiles", self._on_profile, qos)
        self.sub_tf = sn.create_subscription(TFMessage, "/tf", lambda m: self._on_tf(m, False), tf_qos(False))
        self.sub_tf_static = sn.create_subscription(TFMessage, "/tf_static", lambda m: self._on_tf(m, True),
                                                    tf_qos(True))
        self.timer_profiles: Any = sn.create_timer(POLL_PERIOD_S, self._poll_stream)
        group = MutuallyExclusiveCallbackGroup()
        self.sub_scan_active = self.create_subscription(Bool, "scan_active", self._on_scan_active, 10,
                                                        callback_group=group)
        self.srv_start_scan: Any = self.create_service(Trigger, "~/start_scan", lambda q, r: self._on_signal(True, r),
                                                       callback_group=group)
        self.srv_stop_scan: Any = self.create_service(Trigger, "~/stop_scan", lambda q, r: self._on_signal(False, r),
                                                      callback_group=group)
        self._inputs += [self.sub_scan_active, self.srv_start_scan, self.srv_stop_scan]
        self.driver_follower: Any = None
        if values["driver_mapping"]:
            from .driver_params import DriverParameterFollower

            assert self.core is not None
            self.driver_follower = DriverParameterFollower(
                self, str(values["driver_node"]) or None, str(values["driver_mapping"]), self._on_driver_settings,
                defaults=self.core.scanner, scanner=self.core.scanner)
        if self.diag is not None:
            self.diag.settings_from_stream = True
            self.diag.on_profiles(self._stream_values())
        # Spun last, once every attribute its callbacks read exists: a latched /tf_static arrives at once (a CI run
        # lost its whole profile input to a callback that ran before ``driver_follower`` was set).
        self._stream_stop = threading.Event()
        self._stream_executor: SingleThreadedExecutor | None = SingleThreadedExecutor(context=self.context)
        self._stream_executor.add_node(sn)
        self._stream_thread = threading.Thread(target=self._spin_stream, name="xmetro-profiles", daemon=True)
        self._stream_thread.start()

    def _destroy_profile_inputs(self) -> None:
        follower = getattr(self, "driver_follower", None)
        if follower is not None:
            follower.close()
            self.driver_follower = None
        executor = getattr(self, "_stream_executor", None)
        if executor is not None:
            self._stream_stop.set()
            executor.shutdown(timeout_sec=5.0)
            self._stream_thread.join(timeout=5.0)
            self.stream_node.destroy_node()
            self._stream_executor = None
        self.stream = None

    def _spin_stream(self) -> None:
        """The helper's executor loop. A callback that raises is logged and the loop goes on: rclpy's ``spin()``
        would end on it, and with it every profile and tf after (a stream that stalls without a word)."""
        executor = self._stream_executor
        while executor is not None and not self._stream_stop.is_set() and self.context.ok():
            try:
                executor.spin_once(timeout_sec=0.1)
            except (ExternalShutdownException, ShutdownException):
                return
            except Exception as e:
                if self._stream_stop.is_set() or not self.context.ok():
                    return  # shut down while spinning
                what = f"profile input: a callback failed and was skipped: {type(e).__name__}: {e}"
                self.get_logger().error(f"{what}\n{traceback.format_exc(limit=-3)}", throttle_duration_sec=1.0)
                if self.diag is not None:  # a WARN on /diagnostics for loss_warn_period, with the accounting
                    with self._stream_lock:
                        values = self.stream.values() if self.stream is not None else {}
                    self.diag.on_profiles(values, problem=what)

    def _on_driver_settings(self, ds: Any) -> None:
        """The driver's parameters changed: the values it gives (exposure, lateral density) for the next scans."""
        values = {name: float(getattr(ds.settings, name)) for name, src in ds.sources.items()
                  if src == "driver" and name in ("exposure_ms", "lateral_density")}
        with self._stream_lock:
            self._driver_values = values or None
        self.get_logger().info(f"settings from driver {ds.node or ''}: {values or 'none'}")

    def _stream_values(self) -> dict[str, Any]:
        """The stream's accounting and, with a driver mapping, the follower's state (/diagnostics values)."""
        values = self.stream.values() if self.stream is not None else {}
        if self.driver_follower is not None:
            st = self.driver_follower.status()
            values = {**values, **st.values, "driver_settings": st.message}
        return values

    # ------------------------------------------------------------------ callbacks
    def _on_profile(self, msg: PointCloud2, info: Any) -> None:
        # Only queued here: the timer decodes and poses what arrived together (one tf lookup per batch), so that
        # the callback keeps up with a 1 kHz driver while the worker judges.
        lost = self._profile_gaps.add(info)
        with self._stream_lock:
            self._incoming.append(msg)
            if lost and self.stream is not None:
                self.stream.lost(lost)

    def _on_tf(self, msg: Any, static: bool) -> None:
        now = time.monotonic()
        with self._stream_lock:
            if self.stream is None:
                return
            scans, errors, refused = self.stream.tf(msg, static, now)
            if refused:
                self.get_logger().warning(f"{'/tf_static' if static else '/tf'}: {refused} invalid transform(s) "
                                          "refused (non-finite, zero quaternion or unnamed frame)",
                                          throttle_duration_sec=5.0)
            self._dispatch(scans, errors, now)

    def _on_scan_active(self, msg: Bool) -> None:
        self._signal(bool(msg.data))

    def _on_signal(self, start: bool, response: Any) -> Any:
        response.success, response.message = self._signal(start)
        return response

    def _signal(self, start: bool) -> tuple[bool, str]:
        now = time.monotonic()
        with self._stream_lock:
            if self.stream is None:
                return False, "the profile input is not active"
            try:
                scans, errors = self.stream.signal(start, now)
            except ValueError as e:  # scan_trigger is not signal
                return False, str(e)
            self._dispatch(scans, errors, now)
        return True, "scan started" if start else "scan stopped: it is judged once its last profiles are posed"

    def _poll_stream(self) -> None:
        now = time.monotonic()
        with self._stream_lock:
            if self.stream is None:
                return
            if self._incoming:
                batch, self._incoming = self._incoming, []
                self._dispatch(*self.stream.profiles(batch, now), now)
            self._dispatch(*self.stream.poll(now), now)

    # ------------------------------------------------------------------ scans and drops
    def _dispatch(self, scans: list[AssembledScan], errors: list[StreamError], t0: float) -> None:
        """Queue the scans completed and publish the errors. Caller holds the stream lock."""
        core, diag, stream = self.core, self.diag, self.stream
        if core is None or diag is None or stream is None:
            return
        for scan in scans:
            try:
                msg, posed = core.posed_input(scan, self._driver_values)
            except Exception as e:  # never let one scan stop the stream
                stream.not_judged(scan.shape[0])
                errors.append(StreamError(scan_header(scan), "INTERNAL",
                                          f"assembled scan not judged: {type(e).__name__}: {e}"))
                continue
            diag.on_received()
            self._enqueue(core, diag, msg, t0, False, posed)
        for err in errors:
            self._publish_stream_error(err)
        diag.on_profiles(self._stream_values())

    def _publish_stream_error(self, err: StreamError) -> None:
        core, stream = self.core, self.stream
        q = error_quality(err, core.model_id if core is not None else "")
        self.get_logger().error(f"profile stream ({err.code}): {err.message}", throttle_duration_sec=1.0)
        if self.diag is not None and stream is not None:
            self.diag.on_profiles(self._stream_values(), problem=f"profile stream: {err.message}")
        self._publish_quality(q)

    def _posed_done(self, posed: PosedScan, judged: bool) -> None:
        with self._stream_lock:
            if self.stream is not None:
                self.stream.done(posed.profiles, judged)
                if self.diag is not None:
                    self.diag.on_profiles(self._stream_values())

