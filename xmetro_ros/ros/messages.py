"""Messages of the node's outputs and services, built from the core's results (mm → m here, through
:mod:`xmetro_ros.ros.convert`'s unit functions): ``ScanQuality``, ``ReferenceCheck``, ``Explain`` and
``RecommendSettings`` responses.

No DDS: plain message objects, shared by the live node and ``xmetro predict``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from geometry_msgs.msg import Quaternion

from ..judge import flags as fl
from ..msg import ReferenceCheck, ScannerSettings, ScanQuality, SettingsCandidate
from ..scan.targets import published_deviation
from ..srv import Explain, RecommendSettings
from .convert import mm_to_m, settings_to_msg

__all__ = [
    "MAX_ALTERNATIVES",
    "error_code_value",
    "explain_response",
    "failed_response",
    "fill_quality",
    "new_quality",
    "quaternion_msg",
    "recommend_response",
    "reference_message",
]

#: Alternatives listed in a ``RecommendSettings`` response.
MAX_ALTERNATIVES = 20


def error_code_value(code: str) -> int:
    """``ScanQuality.ERROR_<code>`` as an integer (codes: docs/node.md)."""
    return int(getattr(ScanQuality, f"ERROR_{code}"))


def new_quality(header: Any, model_id: str, settings: ScannerSettings | None, defaulted: bool) -> ScanQuality:
    """A ScanQuality for a scan with ``header``, before judging: no verdict, zero counts."""
    q = ScanQuality()
    q.header = header
    q.model_id = model_id
    q.flag_names = list(fl.FLAG_NAMES)
    q.flag_counts = [0] * len(fl.FLAG_NAMES)
    if settings is not None:
        q.settings = settings
    q.settings_defaulted = bool(defaulted)
    return q


def fill_quality(q: ScanQuality, summary: dict[str, Any]) -> ScanQuality:
    """Copy a judged scan's summary (:meth:`xmetro_ros.judge.scan_handler.ScanHandler.summarize`, mm) into ``q`` (m)."""
    q.verdict = int(summary["verdict"])
    q.error_code = ScanQuality.ERROR_NONE
    q.message = summary["message"]
    q.points_received = int(summary["points_received"])
    q.points_valid = int(summary["points_valid"])
    q.points_flagged = int(summary["points_flagged"])
    q.flag_counts = [int(c) for c in summary["flag_counts"]]
    q.mean_abs_error = [mm_to_m(float(v)) for v in summary["mean_abs_error_mm"]]
    q.p95_abs_error = [mm_to_m(float(v)) for v in summary["p95_abs_error_mm"]]
    q.usable_fraction = float(summary["usable_fraction"])
    q.mean_uncertainty = [mm_to_m(float(v)) for v in summary["mean_uncertainty_mm"]]
    q.p95_uncertainty = [mm_to_m(float(v)) for v in summary["p95_uncertainty_mm"]]
    q.decision_rule = str(summary["decision_rule"])
    q.points_conforming, q.points_non_conforming, q.points_undecided = (int(c) for c in summary["decision_counts"])
    return q


_REFERENCE_STATES = {"WARMUP": ReferenceCheck.STATE_WARMUP, "OK": ReferenceCheck.STATE_OK,
                     "WARN": ReferenceCheck.STATE_WARN, "MISMATCH": ReferenceCheck.STATE_MISMATCH}


def reference_message(header: Any, model_id: str, res: Any) -> ReferenceCheck:
    """``ReferenceCheck`` of a reference scan with ``header`` from a ``reference_check.ReferenceResult`` (mm → m)."""
    m = ReferenceCheck()
    m.header = header
    m.model_id = model_id
    m.state = _REFERENCE_STATES[res.state]
    m.reference_scans = int(res.reference_scans)
    m.points = int(res.points)
    m.actual_mean_abs_error = float(mm_to_m(res.actual_mean_abs_mm))
    m.residual_mean = float(mm_to_m(res.residual_mean_mm))
    m.residual_rms = float(mm_to_m(res.residual_rms_mm))
    m.coverage = float(res.coverage)
    st = res.drift
    if st is not None and st.state == "WARN":
        m.statistic, m.detector = st.statistic, st.detector
        m.value, m.threshold = float(st.value), float(st.threshold)
        m.first_warn_scan = int(st.first_warn_scan or 0)
    m.candidate_effect = res.candidate
    m.candidate_rho = float(res.candidate_rho)
    m.candidate_p = float(res.candidate_p)
    m.message = res.message
    return m


def failed_response(response: Any, message: str) -> Any:
    """``response`` (an Explain or RecommendSettings response) marked failed with ``message``."""
    response.success = False
    response.message = message
    return response


def explain_response(result: dict[str, Any], model_id: str, message: str) -> Explain.Response:
    """``~/explain``'s answer from :func:`xmetro_ros.judge.scan_history.explain_rows`'s result (mm → m).

    Explaining the error, the base values, SHAP values and predictions are those of the published deviation
    d = measured − nominal (``published_deviation`` of the model's target: every one flips sign; mean |SHAP| does
    not); explaining U, they are U's (unsigned, unchanged)."""
    signed = published_deviation if str(result.get("output", "error")) == "error" else np.asarray
    resp = Explain.Response()
    resp.model_id = model_id
    resp.success = True
    resp.message = message
    resp.feature_names = result["feature_names"]
    resp.feature_units = result["feature_units"]
    resp.axis_names = result["axis_names"]
    resp.base_values = mm_to_m(signed(result["base_values"])).tolist()
    resp.point_indices = result["point_indices"].astype(np.uint32).tolist()
    resp.shap_values = mm_to_m(signed(result["shap"])).ravel().tolist()
    resp.feature_values = result["features"].ravel().tolist()
    resp.predictions = mm_to_m(signed(result["predictions"])).ravel().tolist()
    resp.output_name = str(result.get("output", "error"))
    resp.mean_abs_shap = mm_to_m(result["mean_abs_shap"]).ravel().tolist()
    return resp


def quaternion_msg(xyzw: Any) -> Quaternion:
    """A geometry_msgs/Quaternion from (x, y, z, w)."""
    x, y, z, w = (float(a) for a in xyzw)
    return Quaternion(x=x, y=y, z=z, w=w)


def recommend_response(rec: Any, frame_id: str, stamp_ns: int, scanner_id: str, tolerance_mm: float,
                       model_id: str) -> RecommendSettings.Response:
    """``~/recommend_settings``' answer from a :class:`xmetro_ros.plan.recommend.Recommendation` (mm → m); candidate
    settings are stamped like the judged scan (``stamp_ns``, ``frame_id``)."""

    def settings_msg(cand: Any) -> ScannerSettings:
        return settings_to_msg(cand.settings, cand.pose, frame_id, stamp_ns, scanner_id)

    b = rec.best
    resp = RecommendSettings.Response()
    resp.model_id = model_id
    resp.success = True
    resp.message = rec.note
    resp.recommended_settings = settings_msg(b)
    resp.recommended_orientation = quaternion_msg(b.quaternion)
    resp.mean_abs_error_before = mm_to_m(rec.before.mean_mm)
    # p95: the total predicted |error| (systematic + random) when the model gives U (Candidate.reported_p95_mm)
    resp.p95_abs_error_before = mm_to_m(rec.before.reported_p95_mm)
    resp.mean_abs_error_after = mm_to_m(b.mean_mm)
    resp.p95_abs_error_after = mm_to_m(b.reported_p95_mm)
    resp.coverage_before = rec.before.coverage
    resp.coverage_after = b.coverage
    resp.meets_tolerance = bool(b.reported_p95_mm <= tolerance_mm)
    resp.alternatives = [
        SettingsCandidate(settings=settings_msg(a), orientation=quaternion_msg(a.quaternion),
                          mean_abs_error=mm_to_m(a.mean_mm), p95_abs_error=mm_to_m(a.reported_p95_mm),
                          coverage=a.coverage, score=mm_to_m(a.score_mm))
        for a in rec.ranked[:MAX_ALTERNATIVES]
    ]
    return resp
