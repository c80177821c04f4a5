"""Helpers of the node tests: simulated scans as clouds, a tester node that publishes into and listens to
xmetro_node, and hand-made malformed clouds."""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import Log
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2, PointField

from xmetro_ros.judge import flags as fl
from xmetro_ros.msg import ScannerSettings, ScanQuality
from xmetro_ros.ros.convert import ns_to_stamp, scan_to_cloud, settings_to_msg
from xmetro_ros.ros.rclpy_util import wait_for
from xmetro_ros.scan.artifacts import Sphere
from xmetro_ros.scan.geometry import HeadPose
from xmetro_ros.scan.scan import Scan
from xmetro_ros.scan.scanner import ScanSettings
from xmetro_ros.sim import simulate_scan

SETTINGS = ScanSettings(6.0, 3.0, 0.5)
TIMEOUT = 30.0


def sim_scan(stamp_ns: int, radius: float = 17.5, settings: ScanSettings = SETTINGS, seed: int = 0) -> Scan:
    return simulate_scan(Sphere(radius, np.zeros(3)), settings, seed=seed, stamp_ns=stamp_ns)


def settings_msg(scan: Scan, stamp_ns: int, frame_id: str = "artifact", **si: float) -> ScannerSettings:
    m = settings_to_msg(scan.settings, scan.pose, frame_id, stamp_ns, scan.scanner_id)
    for k, v in si.items():
        setattr(m, k, v)
    return m


def pose_default() -> HeadPose:
    return HeadPose.looking_down(90.0)


def stamp_ns_of(msg: Any) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def raw_cloud(fields: list[tuple[str, int, int]], point_step: int, n: int, data: bytes | None = None,
              stamp_ns: int = 0, frame_id: str = "artifact", row_step: int | None = None,
              height: int = 1, bigendian: bool = False) -> PointCloud2:
    """A hand-made cloud: fields as (name, offset, datatype)."""
    m = PointCloud2()
    m.header.stamp = ns_to_stamp(stamp_ns)
    m.header.frame_id = frame_id
    m.height = height
    m.width = n // height if height else 0
    m.fields = [PointField(name=nm, offset=o, datatype=dt, count=1) for nm, o, dt in fields]
    m.point_step = point_step
    m.row_step = row_step if row_step is not None else point_step * m.width
    m.is_bigendian = bigendian
    m.is_dense = False
    m.data = data if data is not None else bytes(point_step * n)
    return m


def bigendian_copy(msg: PointCloud2) -> PointCloud2:
    """The same cloud with every field stored big-endian (float32 fields only)."""
    out = PointCloud2()
    out.header = msg.header
    out.height, out.width = msg.height, msg.width
    out.fields = msg.fields
    out.point_step, out.row_step = msg.point_step, msg.row_step
    out.is_dense = msg.is_dense
    out.is_bigendian = True
    raw = np.frombuffer(bytes(msg.data), dtype=np.uint8).reshape(-1, msg.point_step).copy()
    for f in msg.fields:
        assert f.datatype == PointField.FLOAT32
        raw[:, f.offset:f.offset + 4] = raw[:, f.offset:f.offset + 4][:, ::-1]
    out.data = raw.tobytes()
    return out


class NodeClient:
    """Client node: publishes scans / settings to xmetro_node and collects its outputs (thread-safe lists)."""

    def __init__(self, node: Node, target: str = "xmetro_node", best_effort: bool = False) -> None:
        self.node = node
        rel = ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE
        self.pub_scan = node.create_publisher(PointCloud2, "scan", QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=10, reliability=rel, durability=DurabilityPolicy.VOLATILE))
        self.pub_settings = node.create_publisher(ScannerSettings, "scanner_settings", QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.lock = threading.Lock()
        self.quality: list[ScanQuality] = []
        self.deviations: list[PointCloud2] = []
        self.corrected: list[PointCloud2] = []
        self.diagnostics: list[tuple[int, DiagnosticArray]] = []   # (seq, msg)
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
        self.subs = [
            node.create_subscription(ScanQuality, f"/{target}/quality", self._add("quality"), qos),
            node.create_subscription(PointCloud2, f"/{target}/deviations", self._add("deviations"), qos),
            node.create_subscription(PointCloud2, f"/{target}/corrected", self._add("corrected"), qos),
            node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, qos),
        ]
        # the target node's log lines (rcl_interfaces/Log on /rosout): "the node logs it"
        self.logs: list[Log] = []
        node.create_subscription(Log, "/rosout", self._on_log, QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=200, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.VOLATILE))
        self.target = target

    def _add(self, name: str) -> Any:
        def cb(msg: Any) -> None:
            with self.lock:
                getattr(self, name).append(msg)
        return cb

    def _on_log(self, msg: Log) -> None:
        if msg.name == self.target:
            with self.lock:
                self.logs.append(msg)

    def log_mark(self) -> int:
        with self.lock:
            return len(self.logs)

    def wait_log(self, level: int, text: str, mark: int = 0) -> Log:
        """The first log line of the target at ``level`` containing ``text`` after ``mark``."""
        def find() -> Log | None:
            with self.lock:
                return next((m for m in self.logs[mark:] if m.level == level and text in m.msg), None)
        assert wait_for(lambda: find() is not None, TIMEOUT), \
            f"no log line at level {level} with {text!r}: {[m.msg for m in self.logs[mark:]][-5:]}"
        return find()

    def _on_diag(self, msg: DiagnosticArray) -> None:
        with self.lock:
            self.diagnostics.append((len(self.diagnostics), msg))

    def wait_matched(self, target: Any = None) -> None:
        """Wait until this client's endpoints and xmetro_node's are matched. DDS matches each side on its own:
        with ``target`` (the node object, for a node in this process) also wait for the node's side — its scan
        reader matched with our writer (a best-effort reader drops samples from a writer it has not matched yet, and
        nothing resends them) and its output writers with our readers (volatile: nothing written before is
        delivered)."""
        assert wait_for(lambda: self.pub_scan.get_subscription_count() > 0
                        and self.pub_settings.get_subscription_count() > 0
                        and all(s.get_publisher_count() > 0 for s in self.subs), TIMEOUT), "xmetro_node not matched"
        if target is not None:
            assert wait_for(lambda: target.sub_scan.get_publisher_count() > 0
                            and all(p.get_subscription_count() > 0
                                    for p in (target.pub_quality, target.pub_dev, target.pub_corr)),
                            TIMEOUT), "xmetro_node's own endpoints not matched"

    def _find(self, lst: str, stamp: int) -> Any:
        with self.lock:
            for m in getattr(self, lst):
                if stamp_ns_of(m) == stamp:
                    return m
        return None

    def send(self, msg: PointCloud2, outputs: bool | None = None, resend_every: float | None = None
             ) -> tuple[ScanQuality, Any, Any]:
        """Publish a cloud (its stamp must be unique) and wait for its quality (and deviations / corrected unless
        the verdict is ERROR). ``resend_every`` (s): publish again until the quality comes (best-effort QoS)."""
        stamp = stamp_ns_of(msg)
        deadline = time.monotonic() + TIMEOUT
        while True:
            self.pub_scan.publish(msg)
            if wait_for(lambda: self._find("quality", stamp) is not None,
                        resend_every or TIMEOUT) or time.monotonic() > deadline:
                break
        assert self._find("quality", stamp) is not None, f"no quality for {stamp}"
        q = self._find("quality", stamp)
        if outputs is None:
            outputs = q.verdict != ScanQuality.VERDICT_ERROR
        dev = corr = None
        if outputs:
            assert wait_for(lambda: self._find("deviations", stamp) is not None
                            and self._find("corrected", stamp) is not None, TIMEOUT), f"no clouds for {stamp}"
            dev, corr = self._find("deviations", stamp), self._find("corrected", stamp)
            assert_points_accounted(dev)
        return q, dev, corr

    def assert_all_outputs_accounted(self) -> int:
        """:func:`assert_points_accounted` over every ``~/deviations`` received so far; returns how many."""
        with self.lock:
            devs = list(self.deviations)
        for d in devs:
            assert_points_accounted(d)
        return len(devs)

    def diag_mark(self) -> int:
        with self.lock:
            return len(self.diagnostics)

    def wait_diag_level(self, level: int, since: int, pred: Any = None) -> DiagnosticArray:
        """Wait for a /diagnostics message of ``level`` (and ``pred(status)``) received after mark ``since``."""
        def find() -> Any:
            with self.lock:
                for _seq, m in self.diagnostics[since:]:
                    if m.status and m.status[0].level == bytes([level]) and (pred is None or pred(m.status[0])):
                        return m
            return None
        assert wait_for(lambda: find() is not None, TIMEOUT), f"no /diagnostics with level {level}"
        return find()


#: Flags that say why a point has no prediction (xmetro_ros.judge.flags): no return, removed as an outlier,
# non-physical.
NO_PREDICTION_FLAGS = fl.FLAG_INVALID_POINT | fl.FLAG_OUTLIER | fl.FLAG_OUT_OF_VOLUME
#: Flags that say why a point has no uncertainty U: no prediction at all, or a prediction without a finite U.
NO_UNCERTAINTY_FLAGS = NO_PREDICTION_FLAGS | fl.FLAG_NO_UNCERTAINTY


def unaccounted_points(dev: PointCloud2) -> tuple[np.ndarray, np.ndarray]:
    """The points of a ``~/deviations`` cloud that break the node's output invariant, as two boolean masks:
    no finite prediction (dx, dy, dz, dnorm) and no flag saying why (:data:`NO_PREDICTION_FLAGS`); no finite
    U (ux, uy, uz) and no flag saying why (:data:`NO_UNCERTAINTY_FLAGS`)."""
    from xmetro_ros.ros.cloud import xyz_fields

    _, f = xyz_fields(dev, ["dx", "dy", "dz", "dnorm", "ux", "uy", "uz", "flags"])
    flags = np.asarray(f["flags"]).astype(np.uint16)
    finite_d = np.isfinite(f["dx"]) & np.isfinite(f["dy"]) & np.isfinite(f["dz"]) & np.isfinite(f["dnorm"])
    finite_u = np.isfinite(f["ux"]) & np.isfinite(f["uy"]) & np.isfinite(f["uz"])
    return ~finite_d & ((flags & NO_PREDICTION_FLAGS) == 0), ~finite_u & ((flags & NO_UNCERTAINTY_FLAGS) == 0)


def assert_points_accounted(dev: PointCloud2) -> None:
    """The node's output invariant on a ``~/deviations`` cloud: every point has a finite prediction (dx, dy, dz,
    dnorm) and a finite U (ux, uy, uz), or a flag saying why not (:func:`unaccounted_points`) — never NaN with
    flags 0, nor NaN with only flags that do not explain it."""
    silent_d, silent_u = unaccounted_points(dev)
    for what, silent in (("prediction", silent_d), ("uncertainty U", silent_u)):
        assert not silent.any(), (f"{int(silent.sum())} of {len(silent)} published points have no finite {what} "
                                  f"and no flag saying why (stamp {stamp_ns_of(dev)})")


def absurd_scan(stamp_ns: int, value: float = 3e38, share: int = 3) -> Scan:
    """A simulated scan with every ``share``-th finite point set to ``value`` metres on all axes (non-physical)."""
    sc = sim_scan(stamp_ns)
    pts = sc.points.reshape(-1, 3).copy()
    fin = np.flatnonzero(np.isfinite(pts).all(axis=1))
    pts[fin[::share]] = value * 1e3  # scan points are mm
    sc.points = pts.reshape(sc.points.shape)
    return sc


def bad_inputs(stamp: Any, stall: bool = True) -> list[tuple[str, PointCloud2, set[int]]]:
    """A small catalogue of malformed / hostile clouds: (name, cloud, accepted ScanQuality error codes).
    ``stamp()`` gives a fresh unique stamp (ns) per cloud; ``stall``: include issue 12's stall input (last).
    Codes are documented in docs/node.md."""
    f32, i32 = PointField.FLOAT32, PointField.INT32
    xyz = [("x", 0, f32), ("y", 4, f32), ("z", 8, f32)]
    rng = np.random.default_rng(0)
    pts = (np.array([[0.0, 0.0, 0.01]]) + rng.normal(0, 0.001, (60, 3))).astype(np.float32)
    Q = ScanQuality
    out: list[tuple[str, PointCloud2, set[int]]] = [
        ("empty", raw_cloud(xyz, 12, 0, b"", stamp_ns=stamp()), {Q.ERROR_EMPTY_CLOUD}),
        ("truncated data", raw_cloud(xyz, 12, 60, pts.tobytes()[:-12], stamp_ns=stamp()), {Q.ERROR_BAD_LAYOUT}),
        ("row_step too small", raw_cloud(xyz, 12, 60, pts.tobytes(), stamp_ns=stamp(), row_step=100),
         {Q.ERROR_BAD_LAYOUT}),
        ("point_step below fields", raw_cloud(xyz, 8, 60, bytes(8 * 60), stamp_ns=stamp()), {Q.ERROR_BAD_LAYOUT}),
        ("unknown datatype", raw_cloud([*xyz[:2], ("z", 8, 99)], 12, 60, pts.tobytes(), stamp_ns=stamp()),
         {Q.ERROR_BAD_LAYOUT, Q.ERROR_MISSING_FIELD}),
        ("no z", raw_cloud(xyz[:2], 12, 60, pts.tobytes(), stamp_ns=stamp()), {Q.ERROR_MISSING_FIELD}),
        ("integer x", raw_cloud([("x", 0, i32), *xyz[1:]], 12, 60, pts.tobytes(), stamp_ns=stamp()),
         {Q.ERROR_MISSING_FIELD}),
        ("duplicate y", raw_cloud([*xyz, ("y", 12, f32)], 16, 60, bytes(16 * 60), stamp_ns=stamp()),
         {Q.ERROR_DUPLICATE_FIELD}),
        ("all NaN", raw_cloud(xyz, 12, 60, np.full((60, 3), np.nan, np.float32).tobytes(), stamp_ns=stamp()),
         {Q.ERROR_NO_VALID_POINTS}),
        ("all 3e38", raw_cloud(xyz, 12, 60, np.full((60, 3), 3e38, np.float32).tobytes(), stamp_ns=stamp()),
         {Q.ERROR_NO_VALID_POINTS}),
    ]
    # big count claims: 65536 x 65536 points in an empty buffer (4.3e9 points: points_received is 64-bit)
    claim = raw_cloud(xyz, 12, 0, b"", stamp_ns=stamp())
    claim.width, claim.height, claim.row_step = 65536, 65536, 12 * 65536
    out.append(("65536 x 65536 claim", claim, {Q.ERROR_BAD_LAYOUT}))
    # a field claiming count 1,000,000 in a 720-byte cloud (issue 12's stall input, once an hour of quadratic name
    # expansion): the O(fields) layout check rejects it before expanding anything, so BAD_LAYOUT and nothing else
    if stall:
        many = raw_cloud(xyz, 12, 60, pts.tobytes(), stamp_ns=stamp())
        many.fields.append(PointField(name="extra", offset=12, datatype=f32, count=1_000_000))
        out.append(("field count 1,000,000", many, {Q.ERROR_BAD_LAYOUT}))
    return out


def cloud_of(scan: Scan) -> PointCloud2:
    return scan_to_cloud(scan)
