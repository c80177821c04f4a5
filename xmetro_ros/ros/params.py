"""Parameters of ``xmetro_node``: one table with default, unit, meaning, range and whether it may change live.

Loaded from ``config/xmetro.yaml`` (``--ros-args --params-file``). Every parameter is declared with a
``ParameterDescriptor`` (description with unit, numeric range, read-only flag). :func:`validate` is the node's
set-parameters callback body: it rejects unknown choices and inconsistent values with a reason. Read-only
parameters (model, scanner, QoS, pre-processing, history sizes) need a restart; the rest apply to the next scan /
request.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType

from ..judge import flags as fl
from ..judge.scan_handler import HandlerParams
from .convert import m_to_mm

__all__ = ["PARAMS", "ParamSpec", "declare_all", "default_value", "handler_params", "validate", "values_from_node"]


@dataclass(frozen=True)
class ParamSpec:
    """One node parameter: name, default, unit, range / choices, read-only flag and description."""

    name: str
    default: Any
    unit: str
    meaning: str
    lo: float | None = None
    hi: float | None = None
    choices: tuple[str, ...] = ()
    read_only: bool = False


_PI = math.pi
PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("model_dir", "", "path", "model set directory (card.json + ONNX); '' = the shipped default model",
              read_only=True),
    ParamSpec("pose_model_dir", "", "path", "second model set, trained at the recommender's head orientations: it "
              "judges scans taken there that the primary's domain does not hold, and the recommender searches with "
              "it; '' = the shipped pose model when model_dir is '' (else none), 'none' = no second model",
              read_only=True),
    ParamSpec("search_models_dir", "", "path", "pose model sets the recommender searches with together (one "
              "sub-directory each; ranked on their mean, a change advised only beyond their disagreement); '' = the "
              "shipped ensemble when model_dir and pose_model_dir are '' (else none), 'none' = search with the pose "
              "model", read_only=True),
    ParamSpec("scanner_config", "", "path", "scanner YAML; '' = the packaged config/scanners/default.yaml",
              read_only=True),
    ParamSpec("allow_foreign_model", False, "", "use a model set trained for another scanner than scanner_config's "
              "(refused by default: the node starts degraded and says why)", read_only=True),
    ParamSpec("threads", 0, "threads", "the judge's thread budget, shared by its compiled kernels and ONNX Runtime "
              "(they run one after the other); 0 = the CPUs this process may use less one (1 on 2 cores), at most "
              "16", 0, 256, read_only=True),
    ParamSpec("inference_threads", 0, "threads", "ONNX Runtime intra-op threads when not the thread budget's "
              "(0 = threads)", 0, 256, read_only=True),
    ParamSpec("default_lateral_density", 10000.0, "1/m", "settings used when none received: points per metre "
              "along the laser line", 1.0, 1e6),
    ParamSpec("default_direction_density", 4000.0, "1/m", "settings used when none received: profiles per metre "
              "along the scan direction", 1.0, 1e6),
    ParamSpec("default_exposure_time", 0.0005, "s", "settings used when none received: exposure time", 1e-7, 1.0),
    ParamSpec("max_points", 2_000_000, "points", "largest cloud (width x height) processed", 1, 100_000_000),
    ParamSpec("cloud_overflow", "reject", "", "what to do with a cloud over max_points: reject (ERROR) or decimate "
              "(deterministic stride; verdict at least WARN)", choices=("reject", "decimate")),
    ParamSpec("reliability", "auto", "", "QoS reliability of the scan subscription (history depth 5, volatile): "
              "auto follows the topic's publishers (reliable when all of them are, else best_effort; re-checked "
              "every second), best_effort matches every publisher, reliable only reliable ones; the standard "
              "qos_overrides./scan.subscription.reliability parameter wins over it",
              choices=("auto", "reliable", "best_effort"), read_only=True),
    ParamSpec("queue_depth", 4, "scans", "scans waiting for the worker; the oldest is dropped (and counted) "
              "when full", 1, 64, read_only=True),
    ParamSpec("tolerance", 0.0001, "m", "flag OVER_TOLERANCE when the predicted |error| exceeds it; tolerance of "
              "the decision rule", 1e-7, 0.1),
    ParamSpec("decision_rule", "guard_banded", "", "ISO 14253-1 decision rule of the per-point classes: "
              "guard_banded (conforming |d|+U <= tolerance, non-conforming |d|-U > tolerance, else undecided) or "
              "simple (|d| <= tolerance conforming, else non-conforming)", choices=("guard_banded", "simple")),
    ParamSpec("grazing_incidence_deg", 75.0, "deg", "flag GRAZING_INCIDENCE above this incidence angle", 0.0, 90.0),
    ParamSpec("grazing_view_deg", 75.0, "deg", "flag GRAZING_VIEW above this view angle", 0.0, 90.0),
    ParamSpec("domain_margin", 0.05, "fraction", "OUT_OF_DOMAIN margin as a share of each feature's training "
              "range, of the multivariate domain's threshold and of the shape domain's curvature range", 0.0, 10.0),
    ParamSpec("normal_quality_min", 0.3, "0..1", "flag UNRELIABLE_NORMAL below this normal quality", 0.0, 1.0),
    ParamSpec("warn_flagged_fraction", 0.25, "fraction", "WARN when more valid points are flagged", 0.0, 1.0),
    ParamSpec("rescan_usable_fraction", 0.5, "fraction", "RESCAN when fewer valid points are unflagged",
              0.0, 1.0),
    ParamSpec("rescan_over_tolerance_fraction", 0.05, "fraction", "RESCAN when more valid points are over "
              "tolerance", 0.0, 1.0),
    ParamSpec("min_valid_points", 100, "points", "RESCAN with fewer valid points", 0, 10_000_000),
    ParamSpec("outlier_nb_neighbors", 20, "points", "statistical outlier removal: neighbours", 1, 200,
              read_only=True),
    ParamSpec("outlier_std_ratio", 2.0, "sigma", "statistical outlier removal: std ratio", 0.1, 100.0,
              read_only=True),
    ParamSpec("check_frame", True, "", "ERROR FRAME_MISMATCH when the scan frame differs from the settings' frame"),
    ParamSpec("settings_history", 16, "messages", "ScannerSettings kept to pick the one stamped at or before a "
              "scan", 1, 1000, read_only=True),
    ParamSpec("scan_history", 3, "scans", "judged scans kept for ~/explain and ~/recommend_settings", 1, 50,
              read_only=True),
    ParamSpec("explain_max_points", 2000, "points", "cap on points explained per ~/explain request", 1, 100_000),
    ParamSpec("recommend_max_points", 2000, "points", "region subsample cap of ~/recommend_settings "
              "(deterministic, evenly spaced)", 10, 100_000),
    ParamSpec("recommend_max_tilt", 0.2618, "rad", "default tilt search range about head X and Y", 0.0, _PI / 2),
    ParamSpec("recommend_tilt_steps", 3, "steps", "tilt values per axis in [-max, max] (odd keeps 0)", 1, 15),
    ParamSpec("recommend_max_turn", 1.5708, "rad", "default turn search range about head Z", 0.0, _PI),
    ParamSpec("recommend_turn_steps", 3, "steps", "turn values in [-max, max] (odd keeps 0)", 1, 15),
    ParamSpec("recommend_min_coverage", 0.95, "fraction", "discard candidates covering (lit, seen, not grazing) "
              "less of the region than min(this, current coverage)", 0.0, 1.0),
    ParamSpec("recommend_max_seconds", 30.0, "s", "time budget of one ~/recommend_settings search (the current "
              "orientation is always evaluated; the answer says when the search was cut short)", 0.1, 600.0),
    ParamSpec("max_processing_time", 5.0, "s", "watchdog: a scan still processing after this long is abandoned "
              "(ERROR TIMEOUT, checked between stages); a worker that does not come back is reported stalled "
              "(/diagnostics ERROR) and replaced", 0.001, 3600.0),
    ParamSpec("working_volume", 1000.0, "m", "half-width of the working volume (cube about the scan frame's origin): "
              "finite points with a larger |x|, |y| or |z| are non-physical, flagged OUT_OF_VOLUME, no prediction",
              1e-3, 1e6),
    ParamSpec("loss_warn_period", 60.0, "s", "/diagnostics WARN for this long after a scan was lost in transport "
              "(DDS sample-lost event or a gap in a publisher's sequence numbers), with the likely cause and its "
              "fix; 0 = counters only", 0.0, 86400.0),
    ParamSpec("scan_timeout", 5.0, "s", "/diagnostics WARN when no scan arrived for this long (stale input: a "
              "dead scanner is visible)", 0.1, 3600.0),
    ParamSpec("diagnostics_period", 1.0, "s", "period of /diagnostics (also published at once on a level change)",
              0.05, 60.0, read_only=True),
    ParamSpec("reference_radius", 0.0, "m", "certified radius of the reference sphere whose scans arrive on the "
              "reference_scan topic (in-line drift monitoring, ~/reference); 0 = no reference monitoring",
              0.0, 10.0, read_only=True),
    ParamSpec("reference_center", [0.0, 0.0, 0.0], "m", "centre of the reference sphere in the reference scans' "
              "frame (known from the fixture, a CMM or a tracker); ignored with reference_fit_center",
              read_only=True),
    ParamSpec("reference_fit_center", False, "", "fit the reference sphere's centre on each reference scan with "
              "the certified radius (no known position; a drift that shifts the sphere is then invisible)",
              read_only=True),
    ParamSpec("reference_warmup", 10, "scans", "reference scans that set the in-control level of the drift "
              "monitor (EWMA + CUSUM, xmetro_ros/monitor/drift.py)", 3, 1000, read_only=True),
    ParamSpec("reference_max_mismatch", 0.0005, "m", "a reference scan whose median |error| along the normal "
              "exceeds this does not show the declared sphere: MISMATCH, not monitored", 1e-6, 0.1,
              read_only=True),
    ParamSpec("cad_mesh", "", "path", "CAD mesh of the part being scanned (STL, PLY or OBJ; millimetres, part "
              "frame): each judged scan is also compared with it on ~/cad_deviations (measured - CAD along the CAD "
              "normal before and after the compensation, U along the normal) and ~/recommend_settings counts the "
              "part's self-occlusion; '' = off. Needs open3d (the [train] extra)", read_only=True),
    ParamSpec("cad_pose", [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], "m, quaternion", "pose of the CAD part in the scan "
              "frame (part -> scan): x, y, z, qx, qy, qz, qw; applies from the next scan"),
    ParamSpec("cad_register", False, "", "refine cad_pose on each scan by point-to-plane ICP on the compensated "
              "points (xmetro_ros/parts/registration.py; the fit is logged and the registered pose is used for that "
              "scan's map and its recommendation's occlusion)"),
    # Profile streams (docs/profile-streams.md): what line-scanner drivers publish, assembled into scans here.
    ParamSpec("profile_input", False, "", "also subscribe to profiles (one PointCloud2 per laser-line profile in the "
              "sensor frame, metres, as line-scanner drivers publish them) and to /tf and /tf_static: the profiles "
              "are posed by tf, assembled into scans in fixed_frame (scan_trigger) and judged with each profile's "
              "own sensor pose", read_only=True),
    ParamSpec("fixed_frame", "", "frame", "frame of the assembled scans and their outputs (the robot base, the "
              "fixture or the part); required with profile_input", read_only=True),
    ParamSpec("sensor_frame", "", "frame", "tf frame of the profiles' sensor (x along the laser line, z the range); "
              "'' = each profile's header.frame_id", read_only=True),
    ParamSpec("scan_trigger", "gap", "", "what makes a scan of the profiles: count (trigger_count profiles), window "
              "(trigger_window seconds), gap (a pause longer than trigger_gap or the sensor slower than "
              "trigger_min_speed ends it), signal (~/start_scan, ~/stop_scan or the scan_active topic)",
              choices=("count", "window", "gap", "signal"), read_only=True),
    ParamSpec("trigger_count", 500, "profiles", "profiles per scan (scan_trigger count)", 1, 1_000_000,
              read_only=True),
    ParamSpec("trigger_window", 0.5, "s", "scan duration (scan_trigger window)", 1e-3, 3600.0, read_only=True),
    ParamSpec("trigger_gap", 0.05, "s", "a pause between profiles longer than this ends the scan (every trigger; "
              "0 = no gap rule unless scan_trigger is gap)", 0.0, 3600.0, read_only=True),
    ParamSpec("trigger_min_speed", 0.0, "m/s", "the sensor moving slower than this ends the scan and its profiles "
              "are idle (0 = no speed rule)", 0.0, 100.0, read_only=True),
    ParamSpec("stream_context_rows", 0, "profiles", "streaming (scan_trigger count or window): each chunk is judged "
              "with this many profiles of the chunks before and after it, so that its border profiles have "
              "neighbours for their normals, and only its own profiles are published (latency: up to two chunks "
              "plus the judging); 0 = each scan judged on its own", 0, 1000, read_only=True),
    ParamSpec("min_scan_rows", 10, "profiles", "an assembled scan with fewer profiles is not judged (its profiles "
              "are counted dropped, ERROR SHORT_SCAN)", 1, 1_000_000, read_only=True),
    ParamSpec("max_scan_rows", 20000, "profiles", "an assembled scan ends at this many profiles", 1, 1_000_000,
              read_only=True),
    ParamSpec("tf_timeout", 0.5, "s", "how long a profile waits for its tf (stream time) before it is dropped and "
              "reported (ERROR TF_MISSING, TF_NOT_CONNECTED or TF_LATE)", 0.0, 60.0, read_only=True),
    ParamSpec("tf_max_extrapolation", 0.0, "s", "how far past the newest (or before the oldest) tf sample a pose may "
              "be extrapolated; 0 = interpolation only (a guess is never made)", 0.0, 1.0, read_only=True),
    ParamSpec("tf_cache_time", 10.0, "s", "history of the transform buffer", 0.1, 3600.0, read_only=True),
    ParamSpec("profile_columns", "index", "", "where a profile's points go in their scan row: index (point i in column "
              "i: drivers that keep no-returns as +inf or NaN) or ray (by the ray that measured them: drivers that "
              "drop no-returns, e.g. LMI Gocator bridges and the weCat3D Python publisher)",
              choices=("index", "ray"), read_only=True),
    ParamSpec("driver_mapping", "", "", "settings from the line-scanner driver's own ROS parameters, read at start "
              "and followed on /parameter_events: a shipped mapping (scancontrol_lls, scancontrol_samxl; "
              "config/drivers/) or a mapping YAML; '' = none (profile_input only; a ScannerSettings message still "
              "wins)", read_only=True),
    ParamSpec("driver_node", "", "", "the driver node whose parameters driver_mapping reads (e.g. /lls_driver); "
              "'' = the mapping's default node", read_only=True),
    ParamSpec("profile_min_range", 0.0, "m", "points of a profile with z below this are no return (a driver that "
              "passes the sensor's out-of-range value through, e.g. ~0.0322 m on IGMR-RWTH/scancontrol_lls); 0 = "
              "only non-finite points are", 0.0, 10.0, read_only=True),
)
_BY_NAME = {p.name: p for p in PARAMS}
#: Parameters read when the model is loaded (read-only on the plain node; on the lifecycle node settable while
#: unconfigured, e.g. ``model_dir`` for a model changeover).
LOAD_TIME = frozenset(p.name for p in PARAMS if p.read_only)


def default_value(name: str) -> Any:
    """The default of parameter ``name`` (SI units, as in config/xmetro.yaml); KeyError for an unknown name."""
    return _BY_NAME[name].default


def _descriptor(p: ParamSpec, writable: bool = False) -> ParameterDescriptor:
    d = ParameterDescriptor(name=p.name, read_only=p.read_only and not writable)
    unit = f" [{p.unit}]" if p.unit else ""
    choices = f" (one of: {', '.join(p.choices)})" if p.choices else ""
    d.description = f"{p.meaning}{unit}{choices}"
    if p.choices:
        d.additional_constraints = "one of: " + ", ".join(p.choices)
    if isinstance(p.default, bool):
        d.type = ParameterType.PARAMETER_BOOL
    elif isinstance(p.default, int):
        d.type = ParameterType.PARAMETER_INTEGER
        if p.lo is not None and p.hi is not None:
            d.integer_range = [IntegerRange(from_value=int(p.lo), to_value=int(p.hi), step=1)]
    elif isinstance(p.default, list):
        d.type = ParameterType.PARAMETER_DOUBLE_ARRAY
    elif isinstance(p.default, float):
        d.type = ParameterType.PARAMETER_DOUBLE
        if p.lo is not None and p.hi is not None:
            d.floating_point_range = [FloatingPointRange(from_value=float(p.lo), to_value=float(p.hi), step=0.0)]
    else:
        d.type = ParameterType.PARAMETER_STRING
    return d


def declare_all(node: Any, writable: tuple[str, ...] | frozenset[str] = ()) -> None:
    """Declare every parameter of :data:`PARAMS` on ``node`` (values from overrides / params file); the names in
    ``writable`` are declared without their read-only flag (the lifecycle node guards them itself)."""
    for p in PARAMS:
        node.declare_parameter(p.name, p.default, _descriptor(p, p.name in writable))


def validate(changes: dict[str, Any], current: dict[str, Any]) -> str | None:
    """Reason to reject ``changes`` (name → new value) given the ``current`` values, or None when acceptable.

    rclpy already enforces types, numeric ranges and read-only flags from the descriptors; this adds the choices
    and cross-parameter rules, and is also used on the start-up values.
    """
    for name, value in changes.items():
        spec = _BY_NAME.get(name)
        if spec is None:
            continue  # e.g. use_sim_time
        if spec.choices and value not in spec.choices:
            return f"{name} must be one of {', '.join(spec.choices)}, got {value!r}"
        if isinstance(value, float) and not math.isfinite(value):
            return f"{name} must be finite"
        if isinstance(spec.default, list):
            vals = list(value)
            if len(vals) != len(spec.default) or not all(math.isfinite(float(x)) for x in vals):
                return f"{name} must be {len(spec.default)} finite numbers, got {vals}"
            if name == "cad_pose" and sum(float(x) ** 2 for x in vals[3:]) < 1e-12:
                return f"{name}: the quaternion qx, qy, qz, qw is zero"
            continue
        if spec.lo is not None and not isinstance(value, (bool, str)) and not spec.lo <= value <= spec.hi:
            return f"{name} = {value} is outside [{spec.lo:g}, {spec.hi:g}] {spec.unit}"
    merged = {**current, **changes}
    if merged.get("profile_input") and not str(merged.get("fixed_frame", "")).strip():
        return "profile_input needs fixed_frame: the frame the profiles are assembled in (e.g. the robot base)"
    if int(merged.get("stream_context_rows", 0) or 0) > 0 and merged.get("scan_trigger") not in ("count", "window"):
        return "stream_context_rows needs scan_trigger count or window (a stream cut into chunks)"
    return None


def values_from_node(node: Any) -> dict[str, Any]:
    """Current values of all our parameters (arrays as lists of floats)."""
    out = {}
    for p in PARAMS:
        v = node.get_parameter(p.name).value
        out[p.name] = [float(x) for x in v] if isinstance(p.default, list) else v
    return out


def onnx_threads(v: dict[str, Any]) -> int:
    """ONNX Runtime intra-op threads from the node's values: ``inference_threads``, else the thread budget
    (``threads``, 0 = automatic: :func:`xmetro_ros.compute.threads.resolve_threads`)."""
    from ..compute.threads import resolve_threads

    n = int(v.get("inference_threads", 0))
    return n if n > 0 else resolve_threads(int(v.get("threads", 0)))


def handler_params(v: dict[str, Any]) -> HandlerParams:
    """The core's :class:`~xmetro_ros.judge.scan_handler.HandlerParams` (mm) from the node's parameter values (SI)."""
    return HandlerParams(
        tolerance_mm=float(m_to_mm(float(v["tolerance"]))),
        decision_rule=str(v.get("decision_rule", "guard_banded")),
        grazing_incidence_deg=float(v["grazing_incidence_deg"]),
        grazing_view_deg=float(v["grazing_view_deg"]),
        domain_margin=float(v["domain_margin"]),
        normal_quality_min=float(v["normal_quality_min"]),
        thresholds=fl.VerdictThresholds(
            warn_flagged_fraction=float(v["warn_flagged_fraction"]),
            rescan_usable_fraction=float(v["rescan_usable_fraction"]),
            rescan_over_tolerance_fraction=float(v["rescan_over_tolerance_fraction"]),
            min_valid_points=int(v["min_valid_points"]),
        ),
        max_points=int(v["max_points"]),
        cloud_overflow=str(v["cloud_overflow"]),
        outlier_nb_neighbors=int(v["outlier_nb_neighbors"]),
        outlier_std_ratio=float(v["outlier_std_ratio"]),
        working_volume_mm=float(m_to_mm(float(v.get("working_volume", 1000.0)))),
        threads=int(v.get("threads", 0)),
    )
