"""``xmetro_node``: judges laser-scanner point clouds live — per-point predicted errors, flags, verdict, services.

Topics (names relative to the node; ``~`` = the node's private namespace):

- sub ``scan`` (sensor_msgs/PointCloud2, metres; organized or not; float x, y, z required, other fields kept):
  sensor-data QoS (keep last 5, volatile) with the reliability of the ``reliability`` parameter.
- sub ``scanner_settings`` (xmetro_ros/ScannerSettings, reliable, transient-local, depth 10): each scan uses the
  latest settings stamped at or before it (last ``settings_history`` kept); none → the configured defaults
  (ScanQuality.settings_defaulted, /diagnostics WARN).
- pub ``~/deviations`` (PointCloud2: x, y, z, dx, dy, dz, dnorm float32 metres, flags uint16; one point per
  input point, same height × width; predicted error = nominal − measured), ``~/corrected`` (the input cloud, same
  fields, with x, y, z + predicted error; points without a prediction unchanged), ``~/quality`` (ScanQuality),
  ``/diagnostics`` (DiagnosticArray, every ``diagnostics_period`` and at once on a level change).
- services ``~/explain`` (Explain.srv), ``~/recommend_settings`` (RecommendSettings.srv).

Processing runs in a worker thread fed by a bounded queue (``queue_depth``; oldest dropped and counted when full),
so services and parameter changes stay responsive whatever the executor. The computation itself is
:class:`XmetroCore` (no DDS), which ``xmetro predict`` can use offline to produce the very same messages.
"""

from __future__ import annotations

import array
import math
import os
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2, PointField

from . import flags as fl
from . import node_params
from .cloud import new_cloud_message
from .diagnostics import DiagnosticsState
from .explain_service import JudgedScan, ScanHistory, ServiceError, axes_from_mask, explain_rows, select_rows
from .geometry import HeadPose
from .msg import ScannerSettings, ScanQuality, SettingsCandidate
from .scan_handler import HandlerParams, ScanError, ScanHandler
from .scanner import ScannerModel, ScanSettings, SettingsError
from .srv import Explain, RecommendSettings

__all__ = [
    "READY_MESSAGE",
    "CoreOutput",
    "XmetroCore",
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
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def output_qos(depth: int = 10) -> QoSProfile:
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


def _ns(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _error_value(code: str) -> int:
    return int(getattr(ScanQuality, f"ERROR_{code}"))


@dataclass
class _SettingsEntry:
    stamp_ns: int
    msg: ScannerSettings
    settings: ScanSettings | None
    pose: HeadPose | None
    scanner_id: str
    frame_id: str
    error: str


@dataclass
class CoreOutput:
    """Messages for one scan; ``deviations`` / ``corrected`` are None when the scan is in ERROR."""

    quality: ScanQuality
    deviations: PointCloud2 | None
    corrected: PointCloud2 | None
    log: str


class XmetroCore:
    """Everything the node computes, without DDS: settings history, judging clouds, judged scans, services.

    Args:
        values: parameter values (see :mod:`xmetro_ros.node_params`), SI units.
        logger: object with info / warning / error (e.g. an rclpy logger); None → silent.
    """

    def __init__(self, values: dict[str, Any], logger: Any = None) -> None:
        self.values = dict(values)
        self.log = logger
        self.scanner = ScannerModel.load(values["scanner_config"] or None)
        self.model: Any = None
        self.degraded = ""
        try:
            from .features import REGISTRY
            from .inference import ModelSet

            model = ModelSet.load(values["model_dir"] or None, threads=int(values["inference_threads"]))
            model.check_features(REGISTRY)
            self.model = model
        except Exception as e:
            self.degraded = f"model unavailable: {e}"
        self.handler = ScanHandler(self.model, self.scanner, HandlerParams.from_node_values(self.values))
        self._settings: deque[_SettingsEntry] = deque(maxlen=int(values["settings_history"]))
        self._settings_lock = threading.Lock()
        self.history = ScanHistory(int(values["scan_history"]))

    @property
    def model_id(self) -> str:
        return self.model.id if self.model is not None else ""

    def update_values(self, changes: dict[str, Any]) -> None:
        """Apply live parameter changes (already validated)."""
        self.values.update(changes)
        self.handler.params = HandlerParams.from_node_values(self.values)

    # ------------------------------------------------------------------ settings
    def add_settings(self, msg: ScannerSettings) -> str:
        """Store a ScannerSettings message; return "" or the reason it is invalid (kept: scans stamped after it
        get ERROR INVALID_SETTINGS)."""
        from .ros_convert import settings_from_msg

        err = ""
        settings = pose = None
        scanner_id = msg.scanner_id
        try:
            settings, pose, scanner_id, _frame, _stamp = settings_from_msg(msg)
            settings.validate(self.scanner.settings_range)
            if scanner_id and scanner_id != self.scanner.id:
                raise SettingsError(f"scanner_id {scanner_id!r} is not the node's scanner {self.scanner.id!r}")
        except (SettingsError, ValueError) as e:
            err = str(e)
        entry = _SettingsEntry(_ns(msg.header.stamp), msg, settings, pose, scanner_id, msg.header.frame_id, err)
        with self._settings_lock:
            self._settings.append(entry)
            ordered = sorted(self._settings, key=lambda e: e.stamp_ns)
            self._settings.clear()
            self._settings.extend(ordered)
        return err

    def settings_for(self, stamp_ns: int) -> _SettingsEntry | None:
        """The latest settings stamped at or before ``stamp_ns``, or None."""
        with self._settings_lock:
            best = None
            for e in self._settings:
                if e.stamp_ns <= stamp_ns:
                    best = e
            return best

    @property
    def settings_count(self) -> int:
        return len(self._settings)

    def default_entry(self, frame_id: str, stamp_ns: int) -> _SettingsEntry:
        from .ros_convert import settings_to_msg

        v = self.values
        s = ScanSettings.from_si(v["default_lateral_density"], v["default_direction_density"],
                                 v["default_exposure_time"])
        pose = HeadPose.looking_down(self.scanner.standoff_mm)
        msg = settings_to_msg(s, pose, frame_id, stamp_ns, self.scanner.id)
        return _SettingsEntry(stamp_ns, msg, s, pose, self.scanner.id, frame_id, "")

    # ------------------------------------------------------------------ judging
    def _quality(self, header: Any, entry: _SettingsEntry | None, defaulted: bool) -> ScanQuality:
        q = ScanQuality()
        q.header = header
        q.model_id = self.model_id
        q.flag_names = list(fl.FLAG_NAMES)
        q.flag_counts = [0] * len(fl.FLAG_NAMES)
        if entry is not None:
            q.settings = entry.msg
        q.settings_defaulted = bool(defaulted)
        return q

    def _error(self, q: ScanQuality, code: str, message: str, n: int, t0: float) -> CoreOutput:
        q.verdict = ScanQuality.VERDICT_ERROR
        q.error_code = _error_value(code)
        q.message = message
        q.points_received = n
        q.processing_latency = time.monotonic() - t0
        return CoreOutput(q, None, None, f"scan rejected ({code}): {message}")

    def judge(self, msg: PointCloud2, t0: float | None = None) -> CoreOutput:
        """Judge one cloud; ``t0`` = monotonic receipt time (for processing_latency). Never raises for bad input."""
        from .cloud import CloudFormatError, validate_cloud
        from .ros_convert import cloud_to_scan

        t0 = time.monotonic() if t0 is None else t0
        stamp_ns = _ns(msg.header.stamp)
        n = int(msg.width) * int(msg.height)
        entry = self.settings_for(stamp_ns)
        defaulted = entry is None
        if defaulted:
            entry = self.default_entry(msg.header.frame_id, stamp_ns)
        q = self._quality(msg.header, entry, defaulted)
        try:
            if self.model is None:
                return self._error(q, "MODEL_UNAVAILABLE", self.degraded, n, t0)
            validate_cloud(msg, require_valid_points=True)
            if entry.error:
                return self._error(q, "INVALID_SETTINGS", f"settings stamped {entry.stamp_ns} ns are invalid: "
                                                          f"{entry.error}", n, t0)
            if self.values["check_frame"] and not defaulted and entry.frame_id != msg.header.frame_id:
                return self._error(q, "FRAME_MISMATCH", f"scan frame {msg.header.frame_id!r} differs from the "
                                                        f"settings' frame {entry.frame_id!r}", n, t0)
            scan = cloud_to_scan(msg, entry.settings, entry.pose, self.scanner.id)
            res = self.handler.process(scan, settings_defaulted=defaulted)
        except CloudFormatError as e:
            return self._error(q, e.code, str(e), n, t0)
        except ScanError as e:
            return self._error(q, e.code, str(e), n, t0)
        except Exception as e:
            return self._error(q, "INTERNAL", f"{type(e).__name__}: {e}", n, t0)

        try:
            return self._outputs(msg, q, res, entry, stamp_ns, t0)
        except Exception as e:
            return self._error(q, "INTERNAL", f"encoding the outputs failed: {type(e).__name__}: {e}", n, t0)

    def _outputs(self, msg: PointCloud2, q: ScanQuality, res: Any, entry: _SettingsEntry, stamp_ns: int,
                 t0: float) -> CoreOutput:
        from .cloud import dtype_from_fields, xyz_fields

        qd = res.quality
        q.verdict = int(qd["verdict"])
        q.error_code = ScanQuality.ERROR_NONE
        q.message = qd["message"]
        q.points_received = int(qd["points_received"])
        q.points_valid = int(qd["points_valid"])
        q.points_flagged = int(qd["points_flagged"])
        q.flag_counts = [int(c) for c in qd["flag_counts"]]
        q.mean_abs_error = [float(v) * 1e-3 for v in qd["mean_abs_error_mm"]]
        q.p95_abs_error = [float(v) * 1e-3 for v in qd["p95_abs_error_mm"]]
        q.usable_fraction = float(qd["usable_fraction"])
        keep = res.kept
        out_h, out_w = (1, len(keep)) if keep is not None else (int(msg.height), int(msg.width))
        # x, y, z exactly as received (float32 metres), one point per (kept) input point.
        xyz, _ = xyz_fields(msg)
        meas_m = np.asarray(xyz if keep is None else xyz[keep], dtype=np.float32)
        dev_m = (res.deviations * 1e-3).astype(np.float32)
        dnorm = np.sqrt(np.einsum("ij,ij->i", dev_m, dev_m))
        dev_cloud = _create_cloud(msg.header, {
            "x": meas_m[:, 0], "y": meas_m[:, 1], "z": meas_m[:, 2],
            "dx": dev_m[:, 0], "dy": dev_m[:, 1], "dz": dev_m[:, 2], "dnorm": dnorm, "flags": res.flags,
        }, out_h, out_w)
        corrected = _corrected_cloud(msg, dtype_from_fields, res.deviations, keep, out_h, out_w)
        self.history.add(JudgedScan(
            stamp_ns=stamp_ns, frame_id=msg.header.frame_id, n_points=out_h * out_w,
            index=np.asarray(res.prepared.index), points=np.asarray(res.prepared.points), features=res.features,
            predictions=res.predictions, context=_lean_context(res.context), settings=entry.settings, pose=entry.pose,
            scanner_id=self.scanner.id, model_id=self.model_id))
        q.processing_latency = time.monotonic() - t0
        return CoreOutput(q, dev_cloud, corrected, f"scan {stamp_ns}: {qd['verdict_name']} ({qd['message']})")

    # ------------------------------------------------------------------ services
    def explain(self, req: Explain.Request) -> Explain.Response:
        resp = Explain.Response()
        resp.model_id = self.model_id
        try:
            if self.model is None:
                raise ServiceError(self.degraded)
            judged = self.history.get(_ns(req.scan_stamp))
            axes = axes_from_mask(int(req.axes))
            cap_node = int(self.values["explain_max_points"])
            cap = min(int(req.max_points), cap_node) if req.max_points else cap_node
            c = req.region_center
            rows, note = select_rows(judged, np.asarray(req.indices, dtype=np.int64),
                                     np.array([c.x, c.y, c.z]) * 1e3, float(req.region_radius) * 1e3, cap)
            r = explain_rows(self.model, judged, rows, axes)
        except ServiceError as e:
            resp.success = False
            resp.message = str(e)
            return resp
        except Exception as e:
            resp.success = False
            resp.message = f"explanation failed: {type(e).__name__}: {e}"
            return resp
        resp.success = True
        resp.message = note or f"explained {len(rows)} points"
        resp.feature_names = r["feature_names"]
        resp.feature_units = r["feature_units"]
        resp.axis_names = r["axis_names"]
        resp.base_values = (r["base_values"] * 1e-3).tolist()
        resp.point_indices = r["point_indices"].astype(np.uint32).tolist()
        resp.shap_values = (r["shap"] * 1e-3).ravel().tolist()
        resp.feature_values = r["features"].ravel().tolist()
        resp.predictions = (r["predictions"] * 1e-3).ravel().tolist()
        resp.mean_abs_shap = (r["mean_abs_shap"] * 1e-3).ravel().tolist()
        return resp

    def recommend(self, req: RecommendSettings.Request) -> RecommendSettings.Response:
        from .recommend import recommend
        from .ros_convert import settings_from_msg, settings_to_msg

        resp = RecommendSettings.Response()
        resp.model_id = self.model_id
        v = self.values
        try:
            if self.model is None:
                raise ServiceError(self.degraded)
            judged = self.history.get(_ns(req.scan_stamp))
            if judged.settings is None:
                raise ServiceError("the judged scan has no settings")
            c = req.region_center
            big = max(judged.n_points, 1)
            rows, _ = select_rows(judged, np.asarray(req.indices, dtype=np.int64), np.array([c.x, c.y, c.z]) * 1e3,
                                  float(req.region_radius) * 1e3, big)
            cands = []
            for i, m in enumerate(req.candidates):
                try:
                    s, *_ = settings_from_msg(m)
                    cands.append(s.validate(self.scanner.settings_range))
                except (SettingsError, ValueError) as e:
                    raise ServiceError(f"candidate {i}: {e}") from e
            tol_mm = (req.tolerance if req.tolerance > 0 else v["tolerance"]) * 1e3
            max_tilt = v["recommend_max_tilt"] if req.max_tilt == 0 else max(req.max_tilt, 0.0)
            max_turn = v["recommend_max_turn"] if req.max_turn == 0 else max(req.max_turn, 0.0)
            if not (math.isfinite(max_tilt) and math.isfinite(max_turn)):
                raise ServiceError("max_tilt / max_turn must be finite")
            rec = recommend(self.model, judged.context, rows, judged.features, judged.pose, self.scanner,
                            judged.settings, cands or None, max_points=int(v["recommend_max_points"]),
                            max_tilt=max_tilt, tilt_steps=int(v["recommend_tilt_steps"]), max_turn=max_turn,
                            turn_steps=int(v["recommend_turn_steps"]),
                            grazing_incidence_deg=v["grazing_incidence_deg"], grazing_view_deg=v["grazing_view_deg"],
                            min_coverage=v["recommend_min_coverage"], max_seconds=v["recommend_max_seconds"])
        except ServiceError as e:
            resp.success = False
            resp.message = str(e)
            return resp
        except ValueError as e:
            resp.success = False
            resp.message = str(e)
            return resp
        except Exception as e:
            resp.success = False
            resp.message = f"recommendation failed: {type(e).__name__}: {e}"
            return resp

        def to_msg(cand: Any) -> ScannerSettings:
            return settings_to_msg(cand.settings, cand.pose, judged.frame_id, judged.stamp_ns, self.scanner.id)

        def quat(cand: Any) -> Any:
            from geometry_msgs.msg import Quaternion

            x, y, z, w = (float(a) for a in cand.quaternion)
            return Quaternion(x=x, y=y, z=z, w=w)

        b = rec.best
        resp.success = True
        resp.message = rec.note
        resp.recommended_settings = to_msg(b)
        resp.recommended_orientation = quat(b)
        resp.mean_abs_error_before = rec.before.mean_mm * 1e-3
        resp.p95_abs_error_before = rec.before.p95_mm * 1e-3
        resp.mean_abs_error_after = b.mean_mm * 1e-3
        resp.p95_abs_error_after = b.p95_mm * 1e-3
        resp.coverage_before = rec.before.coverage
        resp.coverage_after = b.coverage
        resp.meets_tolerance = bool(b.p95_mm <= tol_mm)
        resp.alternatives = [SettingsCandidate(settings=to_msg(a), orientation=quat(a), mean_abs_error=a.mean_mm * 1e-3,
                                               p95_abs_error=a.p95_mm * 1e-3, coverage=a.coverage,
                                               score=a.score_mm * 1e-3) for a in rec.ranked[:20]]
        return resp


def _lean_context(ctx: Any) -> Any:
    """The feature context without its cache of intermediates (kept in the scan history: memory)."""
    from dataclasses import replace

    try:
        return replace(ctx, _cache={})
    except TypeError:
        return ctx


def _create_cloud(header: Any, arrays: dict[str, np.ndarray], h: int, w: int) -> PointCloud2:
    from .cloud import create_cloud_from_arrays

    return create_cloud_from_arrays(header, arrays, height=h, width=w, is_dense=False)


def _corrected_cloud(msg: PointCloud2, dtype_from_fields: Any, dev_mm: np.ndarray, keep: np.ndarray | None,
                     h: int, w: int) -> PointCloud2:
    """The input cloud (same fields and byte order) with x, y, z + predicted error; unpredicted points unchanged."""
    add = dev_mm.astype(np.float32) * np.float32(1e-3)
    add[~np.isfinite(add)] = 0.0
    by = {f.name: f for f in msg.fields}
    ps = int(msg.point_step)
    fx = by["x"]
    n_out = h * w
    # The message's own array('B') buffer, filled once (assigning bytes would make the message copy them again).
    buf = array.array("B", b"\0") * (n_out * ps)
    fast = (not msg.is_bigendian and sys.byteorder == "little" and ps % 4 == 0 and fx.offset % 4 == 0
            and all(by[a].datatype == PointField.FLOAT32 for a in "xyz")
            and by["y"].offset == fx.offset + 4 and by["z"].offset == fx.offset + 8
            and int(msg.row_step) == ps * int(msg.width))
    if fast and n_out:
        # The common case (our own clouds): one copy of the (kept) records into the buffer, x, y, z adjusted there.
        src = np.frombuffer(msg.data, dtype=np.float32).reshape(-1, ps // 4)
        rec = np.frombuffer(buf, dtype=np.float32).reshape(n_out, ps // 4)
        if keep is not None:
            np.take(src, keep, axis=0, out=rec)
        else:
            rec[:] = src
        c = fx.offset // 4
        rec[:, c:c + 3] += add
        del rec
    elif n_out:
        dt = dtype_from_fields(msg.fields, ps, is_bigendian=bool(msg.is_bigendian))
        raw = np.ndarray(shape=(int(msg.height), int(msg.width)), dtype=dt, buffer=msg.data,
                         strides=(int(msg.row_step), ps)).reshape(-1)
        rec = raw[keep] if keep is not None else raw.copy()
        for i, axis in enumerate(("x", "y", "z")):
            rec[axis] = rec[axis] + add[:, i].astype(rec[axis].dtype)
        np.frombuffer(buf, dtype=np.uint8)[:] = np.ascontiguousarray(rec).reshape(-1).view(np.uint8)
    out = new_cloud_message()  # adopts buf without a copy
    out.header = msg.header
    out.height, out.width = h, w
    out.fields = list(msg.fields)
    out.is_bigendian = bool(msg.is_bigendian)
    out.point_step = int(msg.point_step)
    out.row_step = int(msg.point_step) * w
    out.is_dense = False
    out.data = buf
    return out


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
            self.get_logger().error(f"invalid ScannerSettings stamped {_ns(msg.header.stamp)} ns: {err}")

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

    from .ros_env import apply_ros_env

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
