"""``XmetroCore``: everything the node computes, without DDS — the settings history, judging clouds into the
node's output messages, the history of judged scans and the two services' answers.

Shared by the live node (:mod:`xmetro_ros.ros.node`, in its worker thread) and ``xmetro predict`` (offline), so
both produce the very same messages. Takes and returns ROS message objects (metres); the computation itself is
the ROS-free :class:`xmetro_ros.judge.scan_handler.ScanHandler` (millimetres). Never creates a DDS participant.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from functools import cached_property
from typing import Any

import numpy as np
from sensor_msgs.msg import PointCloud2

from ..judge.inference import LEGACY_SCANNER_ID, model_scanner_id
from ..judge.scan_handler import ScanError, ScanHandler, check_deadline
from ..judge.scan_history import JudgedScan, ScanHistory, ServiceError, axes_from_mask, explain_rows, select_rows
from ..monitor.reference_check import ReferenceChecker, ReferenceResult, ReferenceSpec, live_candidates
from ..msg import ReferenceCheck, ScannerSettings, ScanQuality
from ..scan.assembly import AssembledScan
from ..scan.geometry import HeadPose
from ..scan.scanner import ScannerModel, ScanSettings, SettingsError
from ..srv import Explain, RecommendSettings
from .cloud import CloudFormatError, validate_cloud, xyz_fields
from .convert import (
    cloud_to_scan,
    m_to_mm,
    ns_to_stamp,
    pose7_to_matrix_mm,
    settings_from_msg,
    settings_to_msg,
    stamp_to_ns,
)
from .messages import (
    error_code_value,
    explain_response,
    failed_response,
    fill_quality,
    new_quality,
    recommend_response,
    reference_message,
)
from .output_clouds import cad_cloud, corrected_cloud, deviations_cloud
from .output_clouds import warm_up as warm_output_kernels
from .params import handler_params, onnx_threads
from .posed_scans import PosedScan, assembled_input, choose_settings

__all__ = ["LEGACY_SCANNER_ID", "CoreOutput", "SettingsEntry", "XmetroCore", "load_cad", "model_scanner_id",
           "reference_checker"]

@dataclass
class SettingsEntry:
    """One received ScannerSettings: its stamp (ns), message, decoded values (None when invalid) and error."""

    stamp_ns: int
    msg: ScannerSettings
    settings: ScanSettings | None
    pose: HeadPose | None
    scanner_id: str
    frame_id: str
    error: str


@dataclass
class CoreOutput:
    """Messages for one scan; ``deviations`` / ``corrected`` are None when the scan is in ERROR; ``reference`` is
    the ReferenceCheck of a reference scan (None for other scans); ``cad`` the ``~/cad_deviations`` cloud when a
    CAD part is configured (None otherwise, or when the comparison failed: ``cad_error`` says why, the scan's other
    outputs stand); ``cad_log`` one line on the comparison. ``corrected`` is built on first access (``make_corrected``;
    None: no cloud): the node reads it only while ``~/corrected`` has a subscriber, as drivers publish only the
    clouds someone takes (building and serializing it cost ~8 ms a 167k-point scan here)."""

    quality: ScanQuality
    deviations: PointCloud2 | None
    log: str
    reference: ReferenceCheck | None = None
    cad: PointCloud2 | None = None
    cad_error: str = ""
    cad_log: str = ""
    make_corrected: Callable[[], PointCloud2] | None = None

    @cached_property
    def corrected(self) -> PointCloud2 | None:
        """The ``~/corrected`` cloud (built once, when first asked for), None when the scan is in ERROR."""
        return None if self.make_corrected is None else self.make_corrected()


class XmetroCore:
    """Everything the node computes, without DDS: settings history, judging clouds, judged scans, services.

    Args:
        values: parameter values (see :mod:`xmetro_ros.ros.params`), SI units.
        logger: object with info / warning / error (e.g. an rclpy logger); None → silent.
    """

    def __init__(self, values: dict[str, Any], logger: Any = None) -> None:
        self.values = dict(values)
        self.log = logger
        self.scanner = ScannerModel.load(values["scanner_config"] or None)
        self.model: Any = None
        self.degraded = ""
        try:
            from ..judge.features import REGISTRY
            from ..judge.inference import ModelSet

            model = ModelSet.load(values["model_dir"] or None, threads=onnx_threads(values))
            model.check_features(REGISTRY)
            trained_for = model_scanner_id(model.card)
            if trained_for != self.scanner.id and not values.get("allow_foreign_model", False):
                raise ValueError(f"model {model.id!r} was trained for scanner {trained_for!r}, this node's scanner "
                                 f"is {self.scanner.id!r} (scanner_config); set allow_foreign_model to use it anyway")
            self.model = model
        except Exception as e:
            self.degraded = f"model unavailable: {e}"
        self.pose_model, self.pose_model_error = self._load_pose_model()
        self.search_ensemble, self.search_ensemble_error = self._load_search_ensemble()
        self.handler = ScanHandler(self.model, self.scanner, handler_params(self.values), pose_model=self.pose_model)
        warm_output_kernels()  # the output record kernel, compiled or loaded now rather than on the first scan
        self._settings: deque[SettingsEntry] = deque(maxlen=int(values["settings_history"]))
        self._settings_lock = threading.Lock()
        self.history = ScanHistory(int(values["scan_history"]))
        self.reference = reference_checker(values)
        self.cad, self.cad_error = load_cad(values)

    def _load_pose_model(self) -> tuple[Any, str]:
        """(the second model set or None, why there is none when one was asked for), chosen by
        ``resources.pose_model_path`` from ``model_dir`` and ``pose_model_dir``. It must take the primary's features
        and be trained for the same scanner, and its card's recommender calibration, if any, must be well formed; a
        failure leaves the node judging with the primary alone (logged, on /diagnostics)."""
        from ..judge.inference import load_pose_model
        from ..plan.recommend import recommend_calibration
        from ..scan.resources import pose_model_path

        v = self.values
        path = str(v.get("pose_model_dir", ""))
        where = pose_model_path(v["model_dir"], path)
        if self.model is None or where is None:
            return None, ""
        try:
            pm = load_pose_model(where, self.model, threads=onnx_threads(v))
            recommend_calibration(pm)  # a malformed recommender calibration: refused now, not at the first search
            return pm, ""
        except Exception as e:
            msg = f"pose model set unavailable ({path or 'shipped'}): {e}; judging with {self.model.id!r} alone"
            if self.log is not None:
                self.log.warning(msg)
            return None, msg

    def _load_search_ensemble(self) -> tuple[Any, str]:
        """(the search ensemble or None, why there is none when one was asked for), chosen by
        ``resources.search_models_path`` from ``model_dir``, ``pose_model_dir`` and ``search_models_dir``; a failure
        leaves the search with the pose model (logged, on /diagnostics)."""
        from ..plan.ensemble_search import load_search_ensemble
        from ..scan.resources import search_models_path

        v = self.values
        path = str(v.get("search_models_dir", ""))
        where = search_models_path(v["model_dir"], str(v.get("pose_model_dir", "")), path)
        if self.model is None or where is None:
            return None, ""
        try:
            return load_search_ensemble(where, self.model, threads=onnx_threads(v)), ""
        except Exception as e:
            msg = f"search ensemble unavailable ({path or 'shipped'}): {e}; searching with one model set"
            if self.log is not None:
                self.log.warning(msg)
            return None, msg

    @property
    def model_id(self) -> str:
        return self.model.id if self.model is not None else ""

    def _model_by_id(self, model_id: str) -> Any:
        """The loaded model set with this id (the one that judged a scan): the pose model or the primary."""
        if self.pose_model is not None and model_id == self.pose_model.id:
            return self.pose_model
        return self.model

    @property
    def search_model(self) -> Any:
        """The model set ``~/recommend_settings`` searches with: the search ensemble when loaded, else the pose
        model when loaded (trained at the orientations the search tries), else the primary."""
        if self.search_ensemble is not None:
            return self.search_ensemble
        return self.pose_model if self.pose_model is not None else self.model

    def update_values(self, changes: dict[str, Any]) -> None:
        """Apply live parameter changes (already validated)."""
        self.values.update(changes)
        self.handler.params = handler_params(self.values)

    # ------------------------------------------------------------------ settings
    def add_settings(self, msg: ScannerSettings) -> str:
        """Store a ScannerSettings message; return "" or the reason it is invalid (kept: scans stamped after it
        get ERROR INVALID_SETTINGS)."""
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
        entry = SettingsEntry(stamp_to_ns(msg.header.stamp), msg, settings, pose, scanner_id, msg.header.frame_id, err)
        with self._settings_lock:
            # The same message can arrive twice (the node's transient-local and volatile subscriptions both match
            # a transient-local publisher): one entry per (frame, stamp), the latest received wins.
            for i, old in enumerate(self._settings):
                if old.stamp_ns == entry.stamp_ns and old.frame_id == entry.frame_id:
                    del self._settings[i]
                    break
            self._settings.append(entry)
            ordered = sorted(self._settings, key=lambda e: e.stamp_ns)
            self._settings.clear()
            self._settings.extend(ordered)
        return err

    def settings_for(self, stamp_ns: int) -> SettingsEntry | None:
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

    def default_entry(self, frame_id: str, stamp_ns: int) -> SettingsEntry:
        v = self.values
        s = ScanSettings.from_si(v["default_lateral_density"], v["default_direction_density"],
                                 v["default_exposure_time"])
        pose = HeadPose.looking_down(self.scanner.standoff_mm)
        msg = settings_to_msg(s, pose, frame_id, stamp_ns, self.scanner.id)
        return SettingsEntry(stamp_ns, msg, s, pose, self.scanner.id, frame_id, "")

    def posed_input(self, scan: AssembledScan, driver: Mapping[str, float] | None = None
                    ) -> tuple[PointCloud2, PosedScan]:
        """What :meth:`judge` takes for a scan assembled from profiles: its organized cloud and
        :class:`~xmetro_ros.ros.posed_scans.PosedScan`, with the settings chosen as that module says (a valid
        ScannerSettings stamped at or before the first profile, else the driver's values, the measured densities
        and the defaults)."""
        entry = self.settings_for(int(scan.stamps_ns[0]))
        topic = entry.settings if entry is not None and not entry.error else None
        v = self.values
        defaults = ScanSettings.from_si(v["default_lateral_density"], v["default_direction_density"],
                                        v["default_exposure_time"])
        settings, defaulted, note = choose_settings(scan, topic, driver, defaults, self.scanner)
        return assembled_input(scan, settings, defaulted, note, self.scanner.id)

    # ------------------------------------------------------------------ judging
    def _error(self, q: ScanQuality, code: str, message: str, n: int, t0: float) -> CoreOutput:
        q.verdict = ScanQuality.VERDICT_ERROR
        q.error_code = error_code_value(code)
        q.message = message
        q.points_received = n
        q.processing_latency = time.monotonic() - t0
        return CoreOutput(q, None, f"scan rejected ({code}): {message}")

    def unjudged(self, msg: PointCloud2, code: str, message: str, t0: float | None = None,
                 posed: PosedScan | None = None) -> CoreOutput:
        """An ERROR answer for a scan that is not (or no longer) processed: dropped by the node's queue
        (``QUEUE_OVERFLOW``) or abandoned by the watchdog (``TIMEOUT``). Cheap: no decoding. A scan assembled from
        profiles (``posed``) is answered with its own settings, and a streamed chunk with its own rows' stamp and
        size (not its context's)."""
        t0 = time.monotonic() if t0 is None else t0
        n = int(msg.width) * int(msg.height)
        if posed is not None:
            header = msg.header
            if posed.rows is not None:
                header = restamped(msg.header, posed.stamp_ns)
                n = (posed.rows[1] - posed.rows[0]) * int(msg.width)
            q = new_quality(header, self.model_id, posed.settings_msg, posed.defaulted)
            return self._error(q, code, message, n, t0)
        stamp_ns = stamp_to_ns(msg.header.stamp)
        entry = self.settings_for(stamp_ns)
        q = new_quality(msg.header, self.model_id, entry.msg if entry is not None else None, entry is None)
        return self._error(q, code, message, n, t0)

    def judge(self, msg: PointCloud2, t0: float | None = None, deadline: float | None = None,
              reference: bool = False, posed: PosedScan | None = None) -> CoreOutput:
        """Judge one cloud; ``t0`` = monotonic receipt time (for processing_latency). Never raises for bad input.

        ``reference``: the cloud is a scan of the reference sphere (``reference_scan`` topic): once judged it is
        also checked against the sphere and fed to the drift monitor (``CoreOutput.reference``; see
        :mod:`xmetro_ros.monitor.reference_check`). Without a configured reference (``reference_radius`` 0) it is judged
        like any scan and its ReferenceCheck says so.

        ``deadline`` (``time.monotonic()`` seconds; None = no bound): checked between stages; past it the scan is
        abandoned with ERROR ``TIMEOUT`` (a stage under way is not interrupted). The live node passes now +
        ``max_processing_time``; ``xmetro predict`` passes none, so offline outputs never depend on the machine's speed.

        ``posed``: ``msg`` is a scan assembled from profiles (:mod:`xmetro_ros.ros.posed_scans`): judged with each
        row's own head pose and the settings chosen for it; no frame check (its poses come from tf).
        """
        t0 = time.monotonic() if t0 is None else t0
        out, res = self._judge(msg, t0, deadline, posed)
        if reference:
            out.reference = self._check_reference(msg, res, out)
        return out

    def _judge(self, msg: PointCloud2, t0: float, deadline: float | None,
               posed: PosedScan | None = None) -> tuple[CoreOutput, Any]:
        """``judge`` without the reference check: the messages and the ScanResult (None when in ERROR)."""
        stamp_ns = stamp_to_ns(msg.header.stamp)
        n = int(msg.width) * int(msg.height)
        if posed is not None:
            entry = SettingsEntry(stamp_ns, posed.settings_msg, posed.settings, posed.row_poses.first(),
                                  self.scanner.id, msg.header.frame_id, "")
            defaulted = posed.defaulted
        else:
            found = self.settings_for(stamp_ns)
            defaulted = found is None
            entry = found if found is not None else self.default_entry(msg.header.frame_id, stamp_ns)
        q = new_quality(msg.header, self.model_id, entry.msg, defaulted)
        if posed is not None and posed.rows is not None:  # its outputs, an error's too, carry its own rows' stamp
            q.header = restamped(msg.header, posed.stamp_ns)
        try:
            if self.model is None:
                return self._error(q, "MODEL_UNAVAILABLE", self.degraded, n, t0), None
            validate_cloud(msg, require_valid_points=True)
            check_deadline(deadline, "decoding")
            if entry.error:
                return self._error(q, "INVALID_SETTINGS", f"settings stamped {entry.stamp_ns} ns are invalid: "
                                                          f"{entry.error}", n, t0), None
            if self.values["check_frame"] and posed is None and not defaulted \
                    and entry.frame_id != msg.header.frame_id:
                return self._error(q, "FRAME_MISMATCH", f"scan frame {msg.header.frame_id!r} differs from the "
                                                        f"settings' frame {entry.frame_id!r}", n, t0), None
            if entry.settings is None or entry.pose is None:  # only invalid entries lack them (handled above)
                return self._error(q, "INVALID_SETTINGS", "settings without values", n, t0), None
            scan = cloud_to_scan(msg, entry.settings, entry.pose, self.scanner.id)
            if posed is not None:
                scan = replace(scan, row_poses=posed.row_poses)
            res = self.handler.process(scan, settings_defaulted=defaulted, deadline=deadline)
            if posed is not None and posed.rows is not None:  # a chunk judged with context rows: its own rows
                res = self.handler.crop_rows(res, *posed.rows, settings_defaulted=defaulted)
                msg = cloud_rows(msg, *posed.rows, posed.stamp_ns)
                q.header = msg.header
                stamp_ns, n = posed.stamp_ns, int(msg.width) * int(msg.height)
            check_deadline(deadline, "encoding the outputs")
        except CloudFormatError as e:
            return self._error(q, e.code, str(e), n, t0), None
        except ScanError as e:
            return self._error(q, e.code, str(e), n, t0), None
        except Exception as e:
            return self._error(q, "INTERNAL", f"{type(e).__name__}: {e}", n, t0), None

        try:
            out = self._outputs(msg, q, res, entry, stamp_ns, t0)
            if posed is not None:
                out.quality.message = f"{out.quality.message}; {posed.note}"
                out.log = f"{out.log}; {posed.note}"
            return out, res
        except Exception as e:
            return self._error(q, "INTERNAL", f"encoding the outputs failed: {type(e).__name__}: {e}", n, t0), None

    def _check_reference(self, msg: PointCloud2, res: Any, out: CoreOutput) -> ReferenceCheck:
        """The ReferenceCheck of a judged reference scan (never raises: a failure is a MISMATCH with its reason)."""
        checker = self.reference
        n_mon = checker.monitor.n if checker is not None else 0
        if checker is None:
            r = ReferenceResult("MISMATCH", 0, 0, message="scan on reference_scan but no reference sphere is "
                                                          "configured (reference_radius 0)")
        elif res is None:
            r = ReferenceResult("MISMATCH", n_mon, 0, message=f"reference scan not judged: {out.quality.message}")
        else:
            try:
                r = checker.check(res.prepared.points, res.predictions, res.row_uncertainty,
                                  lambda: live_candidates(res.prepared))
            except Exception as e:
                r = ReferenceResult("MISMATCH", n_mon, 0, message=f"reference check failed: {type(e).__name__}: {e}")
        return reference_message(msg.header, res.model_id if res is not None else self.model_id, r)

    def _outputs(self, msg: PointCloud2, q: ScanQuality, res: Any, entry: SettingsEntry, stamp_ns: int,
                 t0: float) -> CoreOutput:
        fill_quality(q, res.quality)
        q.model_id = res.model_id  # the model set that judged this scan (the pose model's domain may hold it)
        keep = res.kept
        out_h, out_w = (1, len(keep)) if keep is not None else (int(msg.height), int(msg.width))
        # x, y, z exactly as received (float32 metres), one point per (kept) input point.
        xyz, _ = xyz_fields(msg)
        points_m = np.asarray(xyz if keep is None else xyz[keep], dtype=np.float32)
        # The one place the node's sign turns: the model's target t = nominal − measured is published as the
        # deviation d = measured − nominal (docs/conventions.md, "Errors"; deviations_cloud's from_target writes
        # −t, NaN kept); ~/corrected = measured + t = measured − d.
        dev_cloud = deviations_cloud(msg.header, points_m, res.deviations, res.flags, out_h, out_w,
                                     unc_mm=res.uncertainty, from_target=True)
        cad_msg, cad_pose, cad_error, cad_log = self._cad_map(msg, points_m, res)
        self.history.add(JudgedScan(
            stamp_ns=stamp_ns, frame_id=msg.header.frame_id, n_points=out_h * out_w,
            index=np.asarray(res.prepared.index), points=np.asarray(res.prepared.points), features=res.features,
            predictions=res.predictions, context=_lean_context(res.context), settings=entry.settings, pose=entry.pose,
            scanner_id=self.scanner.id, model_id=res.model_id, uncertainty=res.row_uncertainty, cad_pose=cad_pose,
            surface_class=res.surface_class, noise=res.noise, tilt=res.tilt))
        q.processing_latency = time.monotonic() - t0
        qd = res.quality
        # A line a person reads: the scan by its time (s) and frame, its errors and U in µm (SI stays on the topics).
        p95 = "/".join(f"{v * 1e3:.1f}" for v in qd["p95_abs_error_mm"])
        u95 = "/".join("-" if not np.isfinite(v) else f"{v * 1e3:.1f}" for v in qd["p95_uncertainty_mm"])
        line = (f"scan at {stamp_ns / 1e9:.3f} s ({msg.header.frame_id or 'no frame'}): {qd['verdict_name']} "
                f"({qd['message']}); usable {qd['usable_fraction']:.2f} of {qd['points_valid']} valid points, p95 "
                f"|d| x/y/z {p95} µm, p95 U {u95} µm")
        return CoreOutput(q, dev_cloud, line, cad=cad_msg, cad_error=cad_error, cad_log=cad_log,
                          make_corrected=lambda: corrected_cloud(msg, res.deviations, keep, out_h, out_w))

    def _cad_map(self, msg: PointCloud2, points_m: np.ndarray, res: Any
                 ) -> tuple[PointCloud2 | None, np.ndarray | None, str, str]:
        """(``~/cad_deviations`` cloud, pose used (4, 4) mm, error, log line) of a judged scan against the configured
        CAD part; all None / "" without one. A failure (e.g. a registration that cannot converge) is returned as
        the error, never raised: the scan's other outputs stand."""
        if self.cad is None:  # none configured, or it failed to load (said at start-up and on /diagnostics)
            return None, None, "", ""
        from ..parts.cad_judge import cad_deviation

        try:
            pose = pose7_to_matrix_mm(self.values["cad_pose"])
            dev = cad_deviation(self.cad, m_to_mm(points_m), res.deviations, res.uncertainty,
                                flags=res.flags, pose=pose, register=bool(self.values["cad_register"]))
            cloud = cad_cloud(msg.header, points_m[dev.index], dev.index.astype(np.uint32), dev.before, dev.after,
                              dev.u_normal, np.asarray(dev.flags, np.uint16))
        except Exception as e:
            return None, None, f"CAD comparison failed: {type(e).__name__}: {e}", ""
        sm = dev.summary()
        b, a = sm["before"], sm["after"]
        log = (f"CAD {self.cad.name}: {sm['points']} points, |measured - CAD| p95 {b['p95_abs']:.1f} -> "
               f"{a['p95_abs']:.1f} um compensated")
        if dev.registration is not None:
            r = dev.registration
            log += f"; registered: RMSE {r.rmse_mm * 1e3:.1f} um, fitness {r.fitness:.3f}"
        return cloud, dev.pose, "", log

    # ------------------------------------------------------------------ services
    def explain(self, req: Explain.Request) -> Explain.Response:
        """``~/explain``: SHAP values of points of a judged scan (never raises: failures → success false)."""
        try:
            if self.model is None:
                raise ServiceError(self.degraded)
            judged = self.history.get(stamp_to_ns(req.scan_stamp))
            axes = axes_from_mask(int(req.axes))
            cap_node = int(self.values["explain_max_points"])
            cap = min(int(req.max_points), cap_node) if req.max_points else cap_node
            c = req.region_center
            rows, note = select_rows(judged, np.asarray(req.indices, dtype=np.int64), m_to_mm([c.x, c.y, c.z]),
                                     m_to_mm(float(req.region_radius)), cap)
            output = {Explain.Request.OUTPUT_ERROR: "error",
                      Explain.Request.OUTPUT_UNCERTAINTY: "uncertainty"}.get(int(req.output))
            if output is None:
                raise ServiceError(f"unknown output {int(req.output)} (OUTPUT_ERROR=0, OUTPUT_UNCERTAINTY=1)")
            model = self._model_by_id(judged.model_id)  # explained with the model set that judged the scan
            r = explain_rows(model, judged, rows, axes, output=output)
        except ServiceError as e:
            return failed_response(self._explain_base(), str(e))
        except Exception as e:
            return failed_response(self._explain_base(), f"explanation failed: {type(e).__name__}: {e}")
        return explain_response(r, model.id, note or f"explained {len(rows)} points")

    def _explain_base(self) -> Explain.Response:
        resp = Explain.Response()
        resp.model_id = self.model_id
        return resp

    def recommend(self, req: Any, progress: Any = None, cancelled: Any = None) -> RecommendSettings.Response:
        """``~/recommend_settings``: the settings and head orientation predicted to give the smallest error in a
        region of a judged scan (never raises but for a cancel: failures → success false).

        ``req``: a RecommendSettings request or the action's goal (same fields); ``progress`` / ``cancelled``: see
        :func:`xmetro_ros.plan.recommend.recommend` (the action's feedback and cancel).

        Raises:
            RecommendCancelled: ``cancelled()`` became true during the search.
        """
        from ..plan.ensemble_search import search
        from ..plan.recommend import RecommendCancelled

        base = RecommendSettings.Response()
        base.model_id = self.search_model.id if self.model is not None else ""
        v = self.values
        try:
            if self.model is None:
                raise ServiceError(self.degraded)
            judged = self.history.get(stamp_to_ns(req.scan_stamp))
            if judged.settings is None:
                raise ServiceError("the judged scan has no settings")
            c = req.region_center
            big = max(judged.n_points, 1)
            rows, _ = select_rows(judged, np.asarray(req.indices, dtype=np.int64), m_to_mm([c.x, c.y, c.z]),
                                  m_to_mm(float(req.region_radius)), big)
            cands = []
            for i, m in enumerate(req.candidates):
                try:
                    s, *_ = settings_from_msg(m)
                    cands.append(s.validate(self.scanner.settings_range))
                except (SettingsError, ValueError) as e:
                    raise ServiceError(f"candidate {i}: {e}") from e
            tol_mm = m_to_mm(req.tolerance if req.tolerance > 0 else v["tolerance"])
            max_tilt = v["recommend_max_tilt"] if req.max_tilt == 0 else max(req.max_tilt, 0.0)
            max_turn = v["recommend_max_turn"] if req.max_turn == 0 else max(req.max_turn, 0.0)
            if not (math.isfinite(max_tilt) and math.isfinite(max_turn)):
                raise ServiceError("max_tilt / max_turn must be finite")
            rec = search(self.search_model, judged.context, rows, judged.features, judged.pose, self.scanner,
                         judged.settings, cands or None, max_points=int(v["recommend_max_points"]),
                         max_tilt=max_tilt, tilt_steps=int(v["recommend_tilt_steps"]), max_turn=max_turn,
                         turn_steps=int(v["recommend_turn_steps"]),
                         grazing_incidence_deg=v["grazing_incidence_deg"], grazing_view_deg=v["grazing_view_deg"],
                         min_coverage=v["recommend_min_coverage"], max_seconds=v["recommend_max_seconds"],
                         progress=progress, cancelled=cancelled, occluder=self._occluder(judged))
        except RecommendCancelled:
            raise
        except (ServiceError, ValueError) as e:
            return failed_response(base, str(e))
        except Exception as e:
            return failed_response(base, f"recommendation failed: {type(e).__name__}: {e}")
        return recommend_response(rec, judged.frame_id, judged.stamp_ns, self.scanner.id, tol_mm,
                                  self.search_model.id)

    def _occluder(self, judged: JudgedScan) -> Any:
        """The CAD part placed as in the judged scan's CAD map (its self-occlusion for the recommender), or None."""
        if self.cad is None or judged.cad_pose is None:
            return None
        return self.cad.transformed(judged.cad_pose)


def restamped(header: Any, stamp_ns: int) -> Any:
    """A copy of ``header`` (same frame) stamped ``stamp_ns``: a streamed chunk's outputs carry its own first row's."""
    return type(header)(stamp=ns_to_stamp(stamp_ns), frame_id=header.frame_id)


def cloud_rows(msg: PointCloud2, start: int, stop: int, stamp_ns: int) -> PointCloud2:
    """Rows ``start:stop`` of an organized cloud, stamped ``stamp_ns`` (one copy of those rows' bytes)."""
    from copy import copy

    out = copy(msg)
    out.header = restamped(msg.header, stamp_ns)
    out.height = stop - start
    step = int(msg.row_step)
    out.data = bytes(msg.data)[start * step: stop * step]
    return out


def load_cad(values: dict[str, Any]) -> tuple[Any, str]:
    """(the CAD part of the ``cad_mesh`` parameter as a MeshArtifact in its own frame, or None; "" or why it
    could not be loaded). The mesh queries need open3d: checked here, so a missing extra is said at start-up."""
    path = str(values.get("cad_mesh", "") or "")
    if not path:
        return None, ""
    try:
        import open3d  # noqa: F401  (closest points and ray casting of the mesh)

        from ..scan.mesh import MeshArtifact

        return MeshArtifact.from_file(path), ""
    except ImportError as e:
        return None, f"cad_mesh {path}: the CAD comparison needs open3d (pip install 'xmetro_ros[train]'): {e}"
    except Exception as e:
        return None, f"cad_mesh {path} cannot be loaded: {type(e).__name__}: {e}"


def reference_checker(values: dict[str, Any]) -> ReferenceChecker | None:
    """The node's reference checker from its parameters (SI), or None when ``reference_radius`` is 0."""
    from ..monitor.drift import DriftConfig

    radius = float(values.get("reference_radius", 0.0) or 0.0)
    if radius <= 0:
        return None
    c = [float(m_to_mm(float(x))) for x in values.get("reference_center", (0.0, 0.0, 0.0))]
    spec = ReferenceSpec(radius_mm=float(m_to_mm(radius)), center_mm=(c[0], c[1], c[2]),
                         fit_center=bool(values.get("reference_fit_center", False)),
                         max_mismatch_mm=float(m_to_mm(float(values.get("reference_max_mismatch", 0.0005)))))
    return ReferenceChecker(spec, DriftConfig(warmup=int(values.get("reference_warmup", 10))))


def _lean_context(ctx: Any) -> Any:
    """The feature context without its cache of intermediates (kept in the scan history: memory)."""
    try:
        return replace(ctx, _cache={})
    except TypeError:
        return ctx
