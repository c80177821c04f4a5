"""``xmetro_node``: judges laser-scanner point clouds live — per-point predicted errors, flags, verdict, services.

Topics (names relative to the node; ``~`` = the node's private namespace):

- sub ``scan`` (sensor_msgs/PointCloud2, metres; organized or not; float x, y, z required, other fields kept):
  sensor-data QoS (keep last 5, volatile); parameter ``reliability``: ``auto`` (default) follows the topic's
  publishers as rosbag2's recorder does (reliable when every publisher is reliable, so a large cloud's lost fragments
  are resent; else best-effort, which matches every publisher), or fixed ``best_effort`` / ``reliable``.
- sub ``scanner_settings`` (xmetro_ros/ScannerSettings, reliable, depth 10) twice: transient-local (history of a
  latched publisher) and volatile (``ros2 topic pub``, bags replayed without QoS metadata), one handler, a message
  received on both stored once. Each scan uses the latest settings stamped at or before it (last
  ``settings_history`` kept); none → the configured defaults (ScanQuality.settings_defaulted, /diagnostics WARN).
- every subscription's QoS can be overridden with ROS 2's standard parameters, e.g.
  ``qos_overrides./scan.subscription.reliability``, ``qos_overrides./scanner_settings.subscription.durability``,
  ``qos_overrides./scanner_settings.subscription_volatile.reliability`` (read at start / on activate).
- pub ``~/deviations`` (PointCloud2: x, y, z, dx, dy, dz, dnorm, ux, uy, uz float32 metres, flags uint16,
  point_step 44 with every field aligned; one point per input point, same height × width; predicted deviation d =
  measured − nominal, U its expanded uncertainty at 95 %), ``~/corrected`` (the input cloud, same fields, with
  x, y, z − d, residual uncertainty U; points without a prediction unchanged; built and published only while it
  has a subscriber), ``~/quality``
  (ScanQuality), ``/diagnostics`` (DiagnosticArray, every ``diagnostics_period`` and at once on a level change).
- sub ``reference_scan`` (PointCloud2, as ``scan``): scans of the reference sphere (``reference_radius``,
  ``reference_center``): judged like any scan, then checked against the certified sphere and fed to the drift
  monitor; pub ``~/reference`` (ReferenceCheck: residual, coverage, drift state, candidate effect), WARN on
  ``/diagnostics`` on drift (docs/closed-loop.md, "In-line monitoring in the node").
- services ``~/explain`` (Explain.srv), ``~/recommend_settings`` (RecommendSettings.srv), ``~/reset_reference``
  (std_srvs/Trigger: forget the reference stream after a fix); action ``~/recommend_settings``
  (RecommendSettings.action: the same search with feedback and cancel).

Processing runs in a worker thread fed by a bounded queue (``queue_depth``; oldest dropped and counted when full),
so services and parameter changes stay responsive whatever the executor (:mod:`xmetro_ros.ros.worker`, with the
watchdog); the service and action callbacks are in :mod:`xmetro_ros.ros.services`. The computation itself is
:class:`XmetroCore` (no DDS), which ``xmetro predict`` can use offline to produce the very same messages.
"""

from __future__ import annotations

import time
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import SetParametersResult
from rclpy.action import ActionServer, CancelResponse
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from rclpy.subscription import Subscription
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger

from ..action import RecommendSettings as RecommendSettingsAction
from ..compute.malloc import tune_for_scans
from ..msg import ReferenceCheck, ScannerSettings, ScanQuality
from ..srv import Explain, RecommendSettings
from . import params as node_params
from .convert import stamp_to_ns
from .core import XmetroCore
from .diagnostics import DiagnosticsState
from .profile_input import ProfileInput
from .rclpy_util import READY_MESSAGE, SequenceGaps
from .services import ServiceHandlers
from .worker import ScanWorker

__all__ = [
    "XmetroNode",
    "XmetroWiring",
    "main",
    "output_qos",
    "reliability_for_publishers",
    "scan_qos",
    "settings_qos",
]

#: How often ``reliability: auto`` looks at the scan topic's publishers (s).
AUTO_QOS_PERIOD_S = 1.0


def scan_qos(reliability: str = "best_effort", depth: int = 5) -> QoSProfile:
    """Sensor-data QoS of the ``scan`` subscription. Best-effort (the default) matches best-effort drivers and
    reliable publishers alike; reliable matches only reliable publishers."""
    rel = ReliabilityPolicy.RELIABLE if reliability == "reliable" else ReliabilityPolicy.BEST_EFFORT
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=rel,
                      durability=DurabilityPolicy.VOLATILE)


def reliability_for_publishers(offered: list[str]) -> str:
    """``reliability: auto``'s choice for the scan subscription from the reliability each publisher of the topic
    offers (``"reliable"`` / ``"best_effort"``), rosbag2's recorder rule: reliable only when there are publishers and
    every one of them is reliable (a reliable reader never matches a best-effort writer); best effort otherwise.

    A reliable subscription to a reliable publisher gets every fragment of a large cloud resent; a best-effort one
    loses the whole cloud when one fragment is dropped (on Fast DDS's default transports, from a few hundred kB)."""
    return "reliable" if offered and all(o == "reliable" for o in offered) else "best_effort"


def _reliability_name(qos: QoSProfile) -> str:
    """``"reliable"`` or ``"best_effort"`` (the ``reliability`` parameter's words) of a QoS profile."""
    return "reliable" if qos.reliability == ReliabilityPolicy.RELIABLE else "best_effort"


def settings_qos(durability: DurabilityPolicy = DurabilityPolicy.TRANSIENT_LOCAL) -> QoSProfile:
    """QoS of a ``scanner_settings`` subscription (reliable, depth 10; transient-local and volatile: see
    :meth:`XmetroWiring._create_inputs`)."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
                      durability=durability)


def output_qos(depth: int = 10) -> QoSProfile:
    """QoS of the node's publishers: reliable, volatile, keep last ``depth``."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


# The wiring (with its worker and service mixins, type-checked as Nodes) is a mixin of rclpy Node subclasses
# (plain and lifecycle).
class XmetroWiring(ProfileInput, ScanWorker, ServiceHandlers):
    """The node's wiring (parameters, publishers, subscriptions, services, worker), shared by :class:`XmetroNode`
    and ``lifecycle_node.XmetroLifecycleNode``. Mixed into an ``rclpy.node.Node`` subclass; the steps are split so
    that the lifecycle node can run them from its transitions: :meth:`_init_wiring` (parameters, in ``__init__``),
    :meth:`_load_core` (model + scanner), :meth:`_create_outputs`, :meth:`_create_inputs` (subscriptions, services,
    worker, diagnostics timer) and their inverses."""

    core: XmetroCore | None

    def _init_wiring(self, writable: tuple[str, ...] = ()) -> None:
        node_params.declare_all(self, writable=writable)
        self.core = None
        self.diag: DiagnosticsState | None = None
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._work_group = MutuallyExclusiveCallbackGroup()
        self._srv_group = ReentrantCallbackGroup()
        self._init_worker_state()
        # last sequence number seen per publisher (loss accounting)
        self._scan_gaps = SequenceGaps()
        self._inputs: list[Any] = []
        self._outputs: list[Any] = []
        self.timer_diag: Any = None
        self.timer_qos: Any = None

    def _load_core(self) -> XmetroCore:
        """Read and check the parameters, load the model set and the scanner (XmetroCore)."""
        values = node_params.values_from_node(self)
        reason = node_params.validate(values, values)
        if reason:
            raise ValueError(f"invalid parameter: {reason}")
        core = XmetroCore(values, self.get_logger())
        if core.degraded:
            self.get_logger().error(f"starting DEGRADED: {core.degraded}; scans get ERROR MODEL_UNAVAILABLE, "
                                    "services fail")
        if core.cad_error:
            self.get_logger().error(f"{core.cad_error}; scans are judged without the CAD comparison")
        self.diag = DiagnosticsState(self.get_name(), core.scanner.id, core.model_id, core.degraded,
                                     scan_timeout=float(values["scan_timeout"]), cad_mesh=str(values["cad_mesh"]),
                                     cad_error=core.cad_error,
                                     pose_model_id=core.pose_model.id if core.pose_model is not None else "",
                                     pose_model_error="; ".join(e for e in (core.pose_model_error,
                                                                            core.search_ensemble_error) if e))
        self.diag.loss_warn_period = float(values["loss_warn_period"])
        self._qmax = int(values["queue_depth"])
        self.core = core
        return core

    def _create_outputs(self, create: Any) -> None:
        """Publishers, made with ``create`` (``create_publisher`` or ``create_lifecycle_publisher``)."""
        # Clouds: a short writer history (each 180k-point output is ~10 MB; reliable writers keep `depth` samples).
        self.pub_dev = create(PointCloud2, "~/deviations", output_qos(2))
        self.pub_corr = create(PointCloud2, "~/corrected", output_qos(2))
        self.pub_quality = create(ScanQuality, "~/quality", output_qos())
        self.pub_diag = create(DiagnosticArray, "/diagnostics", output_qos())
        self.pub_reference = create(ReferenceCheck, "~/reference", output_qos())
        self.pub_cad = create(PointCloud2, "~/cad_deviations", output_qos(2))  # published with cad_mesh only
        self._outputs = [self.pub_dev, self.pub_corr, self.pub_quality, self.pub_diag, self.pub_reference,
                         self.pub_cad]

    def _create_inputs(self) -> None:
        """Subscriptions (QoS overridable by ``qos_overrides.<topic>.subscription...`` parameters), services, the
        worker thread and the diagnostics timer."""
        assert self.core is not None
        values = self.core.values
        overrides = QoSOverridingOptions.with_default_policies()
        asked = "best_effort" if values["reliability"] == "auto" else values["reliability"]
        self.sub_scan = self._scan_subscription(asked, overrides)
        # `auto`: follow the publishers found (checked every second); a qos_overrides parameter given by the user
        # (command line, params file) wins, as does any override that changed what was asked.
        topic = self.sub_scan.topic_name
        overridden = (f"qos_overrides.{topic}.subscription.reliability" in getattr(self, "_parameter_overrides", {})
                      or _reliability_name(self.sub_scan.qos_profile) != asked)
        auto_qos = values["reliability"] == "auto" and not overridden
        # Reference scans: their own topic (a cell publishes or remaps its reference-artifact scans there), the same
        # QoS and queue as the scans; judged like any scan, then checked against the reference sphere.
        self.sub_reference = self.create_subscription(
            PointCloud2, "reference_scan", self._on_reference_scan, scan_qos(values["reliability"]),
            callback_group=self._work_group, qos_overriding_options=QoSOverridingOptions.with_default_policies())
        # Settings: a transient-local subscription gets the history a latched (transient-local) publisher kept
        # for late joiners, but never matches a volatile publisher (`ros2 topic pub`, a bag replayed without QoS
        # metadata); a volatile one matches both, without history. Both feed one handler; a message received twice
        # (a transient-local publisher matches both) is stored once (XmetroCore.add_settings keys on frame + stamp).
        self.sub_settings = self.create_subscription(
            ScannerSettings, "scanner_settings", self._on_settings, settings_qos(), callback_group=self._work_group,
            qos_overriding_options=overrides)
        self.sub_settings_volatile = self.create_subscription(
            ScannerSettings, "scanner_settings", self._on_settings, settings_qos(DurabilityPolicy.VOLATILE),
            callback_group=self._work_group,
            qos_overriding_options=QoSOverridingOptions.with_default_policies(entity_id="volatile"))
        self.srv_explain = self.create_service(Explain, "~/explain", self._on_explain,
                                               callback_group=self._srv_group)
        self.srv_recommend = self.create_service(RecommendSettings, "~/recommend_settings", self._on_recommend,
                                                 callback_group=self._srv_group)
        # The same search as an action (feedback after each orientation, cancel between them): it can take
        # seconds. Its topics/services live under ~/recommend_settings/_action/, beside the service.
        self.action_recommend = ActionServer(self, RecommendSettingsAction, "~/recommend_settings",
                                             execute_callback=self._execute_recommend,
                                             cancel_callback=lambda _goal: CancelResponse.ACCEPT,
                                             callback_group=self._srv_group)
        self.srv_reset_reference = self.create_service(Trigger, "~/reset_reference", self._on_reset_reference,
                                                       callback_group=self._srv_group)
        self._inputs = [self.sub_scan, self.sub_reference, self.sub_settings, self.sub_settings_volatile,
                        self.srv_explain, self.srv_recommend, self.action_recommend, self.srv_reset_reference]
        if values["profile_input"]:
            self._create_profile_inputs(values)
        # Sequence gaps count only while subscribed: what a publisher sent while the node was inactive was not lost.
        self._scan_gaps.clear()
        with self._cv:
            self._stop = False
            self._queue.clear()
        self._worker = self._start_worker()
        self.timer_diag = self.create_timer(float(values["diagnostics_period"]), self._publish_diag,
                                            callback_group=self._srv_group)
        if auto_qos:
            self._adapt_scan_qos()
            self.timer_qos = self.create_timer(AUTO_QOS_PERIOD_S, self._adapt_scan_qos, callback_group=self._srv_group)
        self._publish_diag()

    def _scan_subscription(self, reliability: str, overrides: QoSOverridingOptions | None) -> Any:
        """The ``scan`` subscription with ``reliability``; ``overrides`` declares (first time) and applies the
        ``qos_overrides`` parameters. /diagnostics is told the reliability it got (its loss message depends on it)."""
        try:
            sub = self.create_subscription(
                PointCloud2, "scan", self._on_scan, scan_qos(reliability), callback_group=self._work_group,
                event_callbacks=self._scan_event_callbacks(), qos_overriding_options=overrides)
        except Exception as e:  # a middleware without the message-lost event: sequence gaps still count losses
            self.get_logger().warning(f"message-lost events unavailable ({type(e).__name__}: {e})")
            sub = self.create_subscription(
                PointCloud2, "scan", self._on_scan, scan_qos(reliability), callback_group=self._work_group,
                qos_overriding_options=overrides)
        if self.diag is not None:
            self.diag.scan_reliability = _reliability_name(sub.qos_profile)
        return sub

    def _adapt_scan_qos(self) -> None:
        """``reliability: auto``: re-create the scan subscription when the publishers' reliability calls for the
        other policy (:func:`reliability_for_publishers`). The swap takes milliseconds; a scan sent meanwhile is
        counted lost by its sequence gap."""
        sub = self.sub_scan
        if sub is None or sub not in self._inputs:
            return
        offered = [_reliability_name(i.qos_profile) for i in self.get_publishers_info_by_topic(sub.topic_name)]
        want = reliability_for_publishers(offered)
        if want == _reliability_name(sub.qos_profile):
            return
        self.destroy_subscription(sub)
        self.sub_scan = self._scan_subscription(want, None)
        self._inputs[self._inputs.index(sub)] = self.sub_scan
        self.get_logger().info(f"scan subscription now {want} to match its {len(offered)} publisher(s) "
                               "(reliability: auto)")

    def _destroy_wiring(self) -> None:
        """What ``destroy_node`` does before ``Node.destroy_node``: :meth:`_destroy_inputs` (the worker, the profile
        input's helper node, and the action server, which ``Node.destroy_node`` leaves: it holds the node's handle,
        so the node and its DDS participant would live until the garbage collector runs). Safe after a part-way
        ``__init__`` (no inputs yet: no worker started)."""
        if hasattr(self, "_inputs"):
            self._destroy_inputs()
        else:
            self._destroy_profile_inputs()

    def _destroy_inputs(self) -> None:
        """Inverse of :meth:`_create_inputs`: no scan is taken or processed afterwards (queued ones are dropped)."""
        for ent in self._inputs:
            if isinstance(ent, Subscription):
                self.destroy_subscription(ent)
            elif isinstance(ent, ActionServer):
                ent.destroy()
            else:
                self.destroy_service(ent)
        self._inputs = []
        if self.timer_diag is not None:
            self.destroy_timer(self.timer_diag)
            self.timer_diag = None
        if self.timer_qos is not None:
            self.destroy_timer(self.timer_qos)
            self.timer_qos = None
        self._destroy_profile_inputs()
        self._stop_worker()

    def _destroy_outputs(self) -> None:
        for pub in self._outputs:
            self.destroy_publisher(pub)
        self._outputs = []

    def _log_ready(self) -> None:
        from .dds_env import dds_env_summary

        assert self.core is not None
        self.get_logger().info(f"DDS environment: {dds_env_summary()}")
        self.get_logger().info(f"{READY_MESSAGE}: model {self.core.model_id or '(none)'}, scanner "
                               f"{self.core.scanner.id}, scan QoS {self.sub_scan.qos_profile.reliability.name}")

    # ------------------------------------------------------------------ callbacks
    def _on_set_parameters(self, params: list[Any]) -> SetParametersResult:
        changes = {p.name: p.value for p in params}
        core = self.core
        current = dict(core.values) if core is not None else node_params.values_from_node(self)
        reason = node_params.validate(changes, current)
        if reason:
            return SetParametersResult(successful=False, reason=reason)
        ours = {k: v for k, v in changes.items() if k in current}
        if core is not None:
            loaded = {k: v for k, v in ours.items() if k in node_params.LOAD_TIME and v != current[k]}
            if loaded:
                return SetParametersResult(successful=False, reason=f"{', '.join(loaded)} take effect when the "
                                           "model is loaded: deactivate and clean up the node first")
            core.update_values(ours)
            if "scan_timeout" in ours and self.diag is not None:
                self.diag.scan_timeout = float(ours["scan_timeout"])
            if "loss_warn_period" in ours and self.diag is not None:
                self.diag.loss_warn_period = float(ours["loss_warn_period"])
        if ours:
            self.get_logger().info(f"parameters changed: {ours}")
        return SetParametersResult(successful=True)

    def _on_settings(self, msg: ScannerSettings) -> None:
        core = self.core
        if core is None:
            return
        err = core.add_settings(msg)
        if self.diag is not None:
            self.diag.on_settings()
        if err:
            self.get_logger().error(f"invalid ScannerSettings stamped {stamp_to_ns(msg.header.stamp)} ns: {err}")

    def _scan_event_callbacks(self) -> SubscriptionEventCallbacks:
        # DDS sample-lost events (rmw_fastrtps reports none for a reader's keep-last history overflow: the sequence
        # gaps below count those); shown apart on /diagnostics.
        return SubscriptionEventCallbacks(
            message_lost=self._on_message_lost)

    def _on_message_lost(self, ev: Any) -> None:
        if self.diag is not None:
            self.diag.on_lost(int(ev.total_count_change), dds_event=True)

    def _count_gaps(self, info: Any) -> None:
        """Scans lost before the callback (:class:`~xmetro_ros.ros.rclpy_util.SequenceGaps`)."""
        lost = self._scan_gaps.add(info)
        if lost and self.diag is not None:
            self.diag.on_lost(lost)

    def _on_reference_scan(self, msg: PointCloud2, info: Any) -> None:
        self._on_scan(msg, info, reference=True)

    def _on_scan(self, msg: PointCloud2, info: Any, reference: bool = False) -> None:
        t0 = time.monotonic()
        core, diag = self.core, self.diag
        if core is None or diag is None:
            return
        self._count_gaps(info)
        diag.on_received()
        self._enqueue(core, diag, msg, t0, reference)

class XmetroNode(XmetroWiring, Node):
    """The live node (see the module docstring). Extra keyword arguments go to ``rclpy.node.Node``
    (``context``, ``parameter_overrides``, ``cli_args``...)."""

    def __init__(self, node_name: str = "xmetro_node", **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self._init_wiring()
        self._load_core()
        self._create_outputs(self.create_publisher)
        self._create_inputs()
        self._log_ready()

    def destroy_node(self) -> None:
        # Also called when __init__ failed part-way: never mask the first error.
        self._destroy_wiring()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Console script ``xmetro_node [--localhost-only] --ros-args --params-file config/xmetro.yaml ...``.

    The DDS environment is the caller's (domain, discovery range, RMW, profile, static peers); only
    ``--localhost-only`` or ``XMETRO_LOCALHOST_ONLY=1`` apply our localhost-only settings (dds_env)."""
    return run_node(XmetroNode, args)


def node_help(prog: str) -> str:
    """``xmetro_node --help``: how to start it and every parameter (name, default, unit, meaning)."""
    import os
    import textwrap

    from .params import PARAMS

    lines = [f"usage: {os.path.basename(prog)} [--localhost-only] [--ros-args -p NAME:=VALUE ... "
             "--params-file FILE]", ""]
    lines += textwrap.wrap(
        "The xmetro node: judges the organized scans it receives (sensor_msgs/PointCloud2 + ScannerSettings), "
        "publishes per-point deviations, their 95 % uncertainty, flags and a verdict; services ~/explain, "
        "~/recommend_settings, ~/reference. The DDS environment is the caller's; --localhost-only (or "
        "XMETRO_LOCALHOST_ONLY=1) keeps it on this machine. docs/node.md describes topics, services and flags.",
        100)
    lines += ["", "parameters:"]
    for p in PARAMS:
        unit = f" [{p.unit}]" if p.unit and p.unit != "path" else ""
        ro = " (read-only)" if p.read_only else ""
        lines += textwrap.wrap(f"{p.name} = {p.default!r}{unit}{ro}: {p.meaning}", 100, initial_indent="  ",
                               subsequent_indent="      ")
    return "\n".join(lines)


def run_node(factory: Any, args: list[str] | None = None) -> int:
    """Start rclpy, build ``factory()`` and spin it on a multi-threaded executor until interrupted."""
    import sys

    from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor

    from .dds_env import apply_requested_ros_env, pop_localhost_flag

    argv, flag = pop_localhost_flag(list(sys.argv if args is None else args))
    own = argv[1:argv.index("--ros-args")] if "--ros-args" in argv else argv[1:]
    if "-h" in own or "--help" in own:  # help, not a node: nothing touches DDS
        print(node_help(argv[0] if argv else "xmetro_node"))
        return 0
    apply_requested_ros_env(flag)
    tune_for_scans()  # glibc's allocator for scan after scan (compute/malloc.py); the environment's settings win
    rclpy.init(args=argv)
    node = None
    try:
        node = factory()
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
