"""The one processing path of a scan (ROS-free), shared by the live node and the offline ``xmetro predict``.

    scan (mm) → point cap → outlier removal + normals (``preprocess.prepare_scan``) → the model's features (names
    from the model card, ``features.compute_features``, float32) → the model set that judges them (the primary, or
    a second "pose" model set when the primary's domain does not hold the scan and its own does:
    :meth:`ScanHandler.route`) → ONNX Runtime inference (x, y, z) and, with a
    calibrated model set, the expanded uncertainty U (95 %) per axis in the same call (same PointNet sets:
    ``ModelSet.predict_with_uncertainty``) → flags and ISO 14253-1 decision classes (:mod:`xmetro_ros.judge.flags`) →
    verdict → quality summary.

Without a calibration U is NaN and every predicted point carries NO_UNCERTAINTY (and is UNDECIDED under the
guard-banded rule); the summary's message says why.

Units: millimetres inside (points, deviations, tolerance_mm); the node converts to metres on its topics.
Deviations here are the model's target, predicted errors ``nominal − measured`` per axis, so ``measured + deviation``
is the corrected point; the node publishes them as d = measured − nominal (``scan.targets.published_deviation``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..compute.threads import use_threads
from ..preprocess.noise import noise_scale
from ..preprocess.tilt_noise import tilt_noise
from ..scan.geometry import HeadPose, RowPoses
from ..scan.scan import Scan
from ..scan.scanner import ScannerModel, SettingsError
from . import flags as fl
from .point_flags import NO_DECISION, base_flags, kept_point_flags, point_masks, scatter_kept
from .surface_class import out_of_principal_domain

__all__ = [
    "NO_DECISION",
    "ROUTE_MAX_OUT_OF_DOMAIN",
    "HandlerParams",
    "ScanError",
    "ScanHandler",
    "ScanResult",
    "cap_points",
    "check_deadline",
    "decimation_index",
    "warm_up",
]

# Below this many valid points outlier removal / normals are meaningless.
_MIN_POINTS_TO_PROCESS = 10


#: A point farther from the laser source than this many times the far end of the scanner's measuring range (or
#: nearer than its near end divided by it) cannot have been measured by it. Wide on purpose: a real scan sits inside
#: the range, up to a few spurious returns.
FOREIGN_RANGE_FACTOR = 10.0
#: A scan with at least this share of such points is another sensor's cloud (a street scene in metres), or
#: coordinates off by a factor 1000: refused whole. (Drivers that write no-returns as (0, 0, 0) leave many points
#: at the frame origin, inside the range: the share, not the median, has to decide.)
FOREIGN_FRACTION = 0.10
#: Points the check looks at, at most (an even subsample): its cost follows the data, never the cloud's size.
FOREIGN_CHECK_POINTS = 4096


def foreign_scan_reason(points: np.ndarray, pose: HeadPose | None, scanner: ScannerModel,
                        posed: tuple[np.ndarray, RowPoses] | None = None) -> str:
    """Why the finite ``points`` (N, 3) mm cannot be a scan of ``scanner`` from ``pose`` ('' when they can).

    The distance of a point from the laser source in the laser plane (``point_geometry``'s source distance: the
    head's motion along the scan direction does not change it) is what a laser line scanner measures; its median
    over the scan must lie within the measuring range widened ``FOREIGN_RANGE_FACTOR`` times for all but
    ``FOREIGN_FRACTION`` of the points. ``posed`` = (pose index of each of ``points`` (N,), the row poses): each
    point's distance from its own profile's source (a head that turns or changes stand-off along the pass); else
    from ``pose``, and without one the study's set-up (looking down from the reference stand-off) is assumed, as
    for defaulted settings."""
    from ..scan.geometry import point_geometry, point_geometry_posed

    if len(points) == 0:
        return ""
    step = max(1, len(points) // FOREIGN_CHECK_POINTS)
    p = np.asarray(np.asarray(points)[::step], dtype=np.float64)
    if posed is not None:
        geo = point_geometry_posed(p, np.asarray(posed[0])[::step], posed[1], scanner.camera_mm)
    else:
        head = pose if pose is not None else HeadPose.looking_down(scanner.standoff_mm)
        geo = point_geometry(p, head, scanner.camera_mm)
    dist = np.asarray(geo.source_distance, dtype=np.float64)
    near, far = (float(v) for v in scanner.depth_of_field_mm)
    hi, lo = FOREIGN_RANGE_FACTOR * far, near / FOREIGN_RANGE_FACTOR
    out = (dist > hi) | (dist < lo)
    share = float(out.mean())
    if share < FOREIGN_FRACTION:
        return ""
    med = float(np.median(dist[out]))
    hint = " (coordinates in mm published as metres?)" if med > 100.0 * far else ""
    return (f"not a laser line scan of this scanner: {100 * share:.0f} % of its points lie outside {lo:g} mm to "
            f"{hi / 1000.0:g} m from the laser source (median {med / 1000.0:.3g} m), where it measures "
            f"{near:g}-{far:g} mm{hint}; another sensor's cloud, wrong units or a wrong head pose. Nothing is "
            "predicted for it.")


#: A scan whose points span fewer than this many profile spacings (1 / direction density) along the scan direction
#: is one laser-line profile (a driver's message), not a scan: it has no neighbours across the scan direction.
SINGLE_PROFILE_SPACINGS = 3.0


def single_profile_reason(points: np.ndarray, pose: HeadPose | None, direction_density_per_mm: float,
                          standoff_mm: float) -> str:
    """Why the finite ``points`` (N, 3) mm are a single profile rather than a scan ('' when they are a scan): their
    extent along the head's scan direction (head +Y of ``pose``; the study's looking-down pose without one) is below
    :data:`SINGLE_PROFILE_SPACINGS` profile spacings. Such points get normals from one line only, so they are judged
    but never better than RESCAN, and the message says why (issue 24: profiles are assembled first)."""
    if len(points) < 2 or direction_density_per_mm <= 0:
        return ""
    p = np.asarray(np.asarray(points)[:: max(1, len(points) // FOREIGN_CHECK_POINTS)], dtype=np.float64)
    head = pose if pose is not None else HeadPose.looking_down(standoff_mm)
    along = p @ np.asarray(head.rotation, dtype=np.float64)[:, 1]
    extent = float(along.max() - along.min())
    spacing = 1.0 / direction_density_per_mm
    if extent >= SINGLE_PROFILE_SPACINGS * spacing:
        return ""
    return (f"a single laser-line profile, not a scan: its points span {extent * 1000:.0f} µm along the scan "
            f"direction (profile spacing {spacing * 1000:.0f} µm), so its normals come from one line and are not "
            "reliable; send scans assembled from many profiles (docs/profile-streams.md)")


class ScanError(ValueError):
    """A scan that cannot be processed. ``code`` is a ScanQuality ERROR_* name without the prefix."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


def check_deadline(deadline: float | None, stage: str) -> None:
    """Abandon a scan whose processing passed ``deadline`` (``time.monotonic()`` seconds; None = no bound).

    Called between stages: Python cannot interrupt a running numpy / ONNX Runtime call, so a stage already under
    way finishes first (see docs/scan-processing.md, watchdog).

    Raises:
        ScanError("TIMEOUT"): past the deadline.
    """
    if deadline is not None:
        now = time.monotonic()
        if now > deadline:
            raise ScanError("TIMEOUT", f"processing exceeded max_processing_time by {now - deadline:.3f} s "
                                       f"(abandoned before {stage})")


@dataclass(frozen=True)
class HandlerParams:
    """Processing parameters (internal units: mm, degrees).

    Attributes:
        tolerance_mm: OVER_TOLERANCE threshold on the predicted |error| norm, and the tolerance of the decision
            rule, mm.
        decision_rule: ISO 14253-1 decision rule of the classes: "guard_banded" | "simple" (flags.DECISION_RULES).
        grazing_incidence_deg, grazing_view_deg: grazing thresholds on acos(N·L), acos(N·V).
        domain_margin: OUT_OF_DOMAIN margin, share of each feature's training range, and of the multivariate
            domain's threshold (flagged above (1 + margin) × threshold).
        normal_quality_min: UNRELIABLE_NORMAL below this normal quality (0..1).
        thresholds: verdict thresholds.
        max_points, cloud_overflow: cap on width × height and what to do above it ("reject" | "decimate").
        outlier_nb_neighbors, outlier_std_ratio: statistical outlier removal.
        working_volume_mm: half-width of the working volume (axis-aligned cube about the scan frame's origin), mm;
            finite points outside it are non-physical: flagged OUT_OF_VOLUME and processed as no return.
        threads: the compiled kernels' threads (0: automatic; the node's ``threads``, xmetro_ros.compute.threads).
    """

    tolerance_mm: float = 0.1
    decision_rule: str = "guard_banded"
    grazing_incidence_deg: float = 75.0
    grazing_view_deg: float = 75.0
    domain_margin: float = 0.05
    normal_quality_min: float = 0.3
    thresholds: fl.VerdictThresholds = field(default_factory=fl.VerdictThresholds)
    max_points: int = 2_000_000
    cloud_overflow: str = "reject"
    outlier_nb_neighbors: int = 20
    outlier_std_ratio: float = 2.0
    working_volume_mm: float = 1_000_000.0
    threads: int = 0  # the thread budget of the compiled kernels (0: automatic, xmetro_ros.compute.threads)


@dataclass
class ScanResult:
    """Outcome of :meth:`ScanHandler.process`.

    Attributes:
        deviations: (N, 3) float64 mm predicted error per point of the (possibly decimated) scan, flat order;
            NaN for points without a prediction (invalid, outlier).
        flags: (N,) uint16 flag bits.
        quality: summary dict (see :meth:`ScanHandler.summarize`), mm units.
        prepared: the ``preprocess.Prepared`` of the kept points.
        features: (M, F) float32 model features of the kept points (rows of ``prepared``).
        predictions: (M, 3) float64 mm model output for those rows.
        context: the ``features.FeatureContext`` (for the recommender).
        scan: the scan actually processed (after the point cap).
        kept: flat indices of the input points kept by the point cap (None: all, not decimated).
        uncertainty: (N, 3) float64 mm expanded uncertainty U (95 %) per point of the scan, flat order; NaN where
            there is no prediction or no calibration (flag NO_UNCERTAINTY).
        row_uncertainty: (M, 3) float64 mm U for the rows of ``prepared`` (same order as ``predictions``).
        decisions: (N,) uint8 decision class (flags.CONFORMING / NON_CONFORMING / UNDECIDED) per point; 255 where
            there is no prediction.
        shape_out_of_domain: (M,) bool per row of ``prepared``: a surface shape (mean curvature) outside the model's
            calibration shapes (flagged OUT_OF_DOMAIN and DOMAIN_SHAPE, U not widened); None when the card has no
            ``domain_shape``.
        surface_class: (M,) int8 surface class of each row of ``prepared`` whose multipliers its U took
            (:meth:`ModelSet.surface_classes`; −1 none), None when the card is not calibrated per class.
        noise: (M,) float64 measured noise (mm, along the normal; :mod:`xmetro_ros.preprocess.noise`) of each row of
            ``prepared`` that its U took (NaN: none), None when the card's U does not use it.
        model_id: id of the model set that judged the scan (the primary, or the pose model: :meth:`ScanHandler.route`).
        tilt: (M, 3) float64 measured tilt noise (radians; :mod:`xmetro_ros.preprocess.tilt_noise`) of each row of
            ``prepared`` that the card's along-normal allowance took (NaN: none), None when it takes none.
    """

    deviations: np.ndarray
    flags: np.ndarray
    quality: dict[str, Any]
    prepared: Any
    features: np.ndarray
    predictions: np.ndarray
    context: Any
    scan: Scan
    kept: np.ndarray | None = None
    uncertainty: np.ndarray | None = None
    row_uncertainty: np.ndarray | None = None
    decisions: np.ndarray | None = None
    shape_out_of_domain: np.ndarray | None = None
    surface_class: np.ndarray | None = None
    noise: np.ndarray | None = None
    model_id: str = ""
    tilt: np.ndarray | None = None


def warm_up() -> float:
    """Compile, or load from numba's on-disk cache, the compiled kernels of the judge path (grid pre-processing,
    summary statistics) so the first scan does not pay for it: 0.5-1 s per process from numba's disk cache; on the
    very first run of an installation (empty cache) the node took 116-118 s to be ready on this 2-core machine,
    idle (0.7.3, `xmetro_node` with NUMBA_CACHE_DIR empty). Returns the seconds taken."""
    import time

    from ..preprocess import curvature, grid_kernels, noise
    from ..preprocess import tilt_noise as tilt_kernels
    from . import along_normal, scan_stats

    t = time.perf_counter()
    grid_kernels.warm_up()
    noise.warm_up()
    tilt_kernels.warm_up()
    along_normal.warm_up()
    for fn in (curvature.grid_mean_curvature, curvature.grid_principal_curvatures):
        fn(np.zeros((1, 3)), np.ones((1, 3), np.float32), np.zeros(1, np.int64), (2, 2), 1.0, 1.0)
    from ..preprocess import knn_grid
    from ..preprocess.knn import _knn_normals
    from ..preprocess.points import has_duplicates
    from .surface_class import out_of_principal_domain

    knn_grid.warm_up()
    has_duplicates(np.zeros((2, 3)))
    out_of_principal_domain(np.zeros((1, 2)), np.ones((1, 1), bool), 0.0, 1.0)
    _knn_normals(np.eye(3), np.arange(3), np.zeros((3, 3)), np.tile(np.arange(3), (3, 1)), np.ones(3, bool), 1.0)
    flags = np.array([0, 1, 3, 64], np.uint16)
    scan_stats.flag_tally(flags, fl.FLAG_BITS)
    scan_stats.abs_error_stats(np.ones((4, 3)), flags > 0)
    scan_stats.abs_error_stats(np.ones((4, 3)))
    scan_stats.abs_error_stats(np.ones((scan_stats._SAMPLED_FROM, 3)))  # the sampled bracket of large columns
    from . import point_flags

    point_flags.warm_up()
    from ..scan.geometry import HeadPose, point_geometry, point_geometry_posed, rotation_xyz

    for pose in (HeadPose(np.zeros(3), np.eye(3)), HeadPose(np.zeros(3), rotation_xyz(0.1, 0.0, 0.0))):
        for dt in (np.float32, np.float64):
            point_geometry(np.ones((1, 3)), pose, 10.0, dtype=dt)

    rp = RowPoses(np.zeros((1, 3)), np.eye(3)[None], np.zeros(1, np.int32))
    point_geometry_posed(np.ones((1, 3)), np.zeros(1, np.int64), rp, np.array([10.0, 0.0, 0.0]))
    return time.perf_counter() - t


def decimation_index(n: int, max_points: int) -> np.ndarray:
    """Deterministic evenly spaced subset of ``range(n)`` with at most ``max_points`` entries."""
    if n <= max_points:
        return np.arange(n)
    stride = -(-n // max_points)
    return np.arange(0, n, stride)


def cap_points(scan: Scan, max_points: int, overflow: str) -> tuple[Scan, np.ndarray | None]:
    """Apply the point cap: the scan unchanged (None), or a decimated unorganized copy and the kept flat indices.

    Raises:
        ScanError("TOO_MANY_POINTS"): over the cap with ``overflow == "reject"``.
    """
    n = int(np.prod(scan.shape))
    if n <= max_points:
        return scan, None
    if overflow != "decimate":
        raise ScanError("TOO_MANY_POINTS", f"cloud has {n} points > max_points {max_points} (cloud_overflow=reject)")
    keep = decimation_index(n, max_points)
    pts = np.asarray(scan.points).reshape(-1, 3)[keep]
    fields = {k: np.asarray(v).reshape(-1)[keep] for k, v in scan.fields.items()}
    exp = None if scan.expected_error is None else np.asarray(scan.expected_error).reshape(-1, 3)[keep]
    std = None if scan.noise_std is None else np.asarray(scan.noise_std).reshape(-1, 3)[keep]
    inj = None if scan.injected_outlier is None else np.asarray(scan.injected_outlier).reshape(-1)[keep]
    rp = None if scan.row_poses is None else scan.row_poses.take(keep)
    return replace(scan, points=pts, fields=fields, expected_error=exp, noise_std=std, injected_outlier=inj,
                   row_poses=rp), keep


#: A scan is judged by the pose model only when more than this share of its points lies outside the primary model's
#: multivariate domain (the recommender's ``max_out_of_domain``) and a smaller share outside the pose model's.
ROUTE_MAX_OUT_OF_DOMAIN = 0.05
#: Rows of a scan the routing decision looks at (evenly spaced): the shares, not the points, decide.
ROUTE_ROWS = 2000
#: The scan's head orientation must be closer, by this much (rad), to one the pose model was trained at than to
#: any the primary was trained at (a looking-down scan of a part stays with the primary, out of domain or not).
ROUTE_ANGLE_MARGIN = float(np.radians(1.0))


def _nearest_angle(rotation: np.ndarray, rotations: list[np.ndarray]) -> float:
    """Smallest rotation angle (rad) between ``rotation`` and any of ``rotations``."""
    tr = np.array([np.trace(rotation.T @ r) for r in rotations])
    return float(np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0)).min())


class ScanHandler:
    """Judge scans with a model set, or with the better-suited of two.

    Args:
        model_set: the primary ``inference.ModelSet`` (feature names, domain, predict).
        scanner: the scanner model (settings range, baseline).
        params: processing parameters; replace ``handler.params`` to change them live.
        pose_model: optional second model set with the same features, trained at other head orientations (the
            rescan recommender's): a scan goes to it when the primary's domain does not hold it and the pose
            model's holds more of it (:meth:`route`).
    """

    def __init__(self, model_set: Any, scanner: ScannerModel, params: HandlerParams | None = None,
                 pose_model: Any = None) -> None:
        self.model = model_set
        self.pose_model = pose_model
        self.scanner = scanner
        self.params = params or HandlerParams()
        self.warm_up_s = warm_up()

    def route(self, X: np.ndarray, rotation: np.ndarray | None = None) -> Any:
        """The model set to judge feature rows X (M, F) of a scan taken with head ``rotation`` (3×3, scan frame)
        with: the primary, unless (1) the head orientation is closer (by ``ROUTE_ANGLE_MARGIN``) to one the pose
        model was trained at than to any the primary was (``ModelSet.training_rotations``; skipped when either card
        does not say or ``rotation`` is None), (2) more than ``ROUTE_MAX_OUT_OF_DOMAIN`` of the rows lie outside the
        primary's multivariate domain (threshold widened by ``domain_margin``, as the flags) and (3) a smaller share
        outside the pose model's. Decided on at most ``ROUTE_ROWS`` evenly spaced rows (~0.1 ms); the judged scan's
        flags and U are the chosen model's own."""
        if self.pose_model is None or len(X) == 0:
            return self.model
        rp = getattr(self.model, "training_rotations", None)
        rq = getattr(self.pose_model, "training_rotations", None)
        if rotation is not None and rp is not None and rq is not None:
            r = np.asarray(rotation, np.float64)
            if _nearest_angle(r, rq) >= _nearest_angle(r, rp) - ROUTE_ANGLE_MARGIN:
                return self.model
        rows = X[np.unique(np.linspace(0, len(X) - 1, min(len(X), ROUTE_ROWS)).astype(np.int64))]
        rows = rows[np.isfinite(rows).all(axis=1)]
        if len(rows) == 0:
            return self.model
        margin = self.params.domain_margin
        primary = float(np.mean(self.model.out_of_domain_mv(rows, margin=margin)))
        if primary <= ROUTE_MAX_OUT_OF_DOMAIN:
            return self.model
        return self.pose_model if np.mean(self.pose_model.out_of_domain_mv(rows, margin=margin)) < primary \
            else self.model


    def preprocess_config(self) -> Any:
        from ..preprocess import PreprocessConfig

        return PreprocessConfig(nb_neighbors=self.params.outlier_nb_neighbors, std_ratio=self.params.outlier_std_ratio)

    def process(self, scan: Scan, settings_defaulted: bool = False, deadline: float | None = None) -> ScanResult:
        """Judge one scan (see the module docstring). ``deadline``: ``time.monotonic()`` after which the scan is
        abandoned (checked between stages, :func:`check_deadline`).

        Every point gets either a finite prediction or a flag saying why not (OUT_OF_VOLUME, INVALID_POINT,
        OUTLIER): non-physical coordinates never come out as NaN with flags 0.

        Raises:
            ScanError: with the ScanQuality error code (TOO_MANY_POINTS, NO_VALID_POINTS, INVALID_SETTINGS,
                MISSING_INPUT_FIELD, MODEL_UNAVAILABLE, TIMEOUT).
        """
        from ..preprocess import PreprocessError, prepare_scan
        from .features import FeatureContext, MissingFieldError, compute_features

        p = self.params
        if self.model is None:
            raise ScanError("MODEL_UNAVAILABLE", "no model loaded")
        use_threads(p.threads)  # numba's count is the calling thread's: this judge's, whatever thread runs it
        scan, kept = cap_points(scan, p.max_points, p.cloud_overflow)
        try:
            scan.settings.validate(self.scanner.settings_range)
        except SettingsError as e:
            raise ScanError("INVALID_SETTINGS", f"invalid scan settings: {e}") from e
        n = int(np.prod(scan.shape))
        if n == 0:
            raise ScanError("EMPTY_CLOUD", "the scan has no points")
        finite_xyz, outside, n_valid = point_masks(scan.points, p.working_volume_mm)
        any_outside = bool(outside.any())
        if any_outside:
            # Non-physical points are processed as no return (NaN), so no stage sees them (3e38 m would overflow).
            pts = np.array(scan.points, dtype=np.float64)
            pts.reshape(-1, 3)[outside] = np.nan
            scan = replace(scan, points=pts)
        valid = finite_xyz & ~outside
        if n_valid == 0:
            if any_outside:
                raise ScanError("NO_VALID_POINTS", f"all {n} points are NaN/Inf or outside the working volume "
                                                   f"(|coordinate| > {p.working_volume_mm / 1e3:g} m)")
            raise ScanError("NO_VALID_POINTS", f"all {n} points are NaN/Inf")
        if n_valid < _MIN_POINTS_TO_PROCESS:
            raise ScanError("NO_VALID_POINTS", f"only {n_valid} finite points (< {_MIN_POINTS_TO_PROCESS})")
        missing = sorted(set(self.model.required_fields()) - set(scan.fields))
        if missing:
            raise ScanError("MISSING_INPUT_FIELD", f"the model needs per-point field(s) {', '.join(missing)} "
                                                   f"that the cloud lacks (has: {', '.join(sorted(scan.fields))})")
        # The two checks below read every step-th valid point (FOREIGN_CHECK_POINTS of them): gather those alone
        # (the same points the checks would pick from all valid ones).
        vidx = np.flatnonzero(valid)[:: max(1, n_valid // FOREIGN_CHECK_POINTS)]
        valid_pts = scan.points.reshape(-1, 3)[vidx]
        posed = None
        if scan.row_poses is not None:
            posed = (scan.row_poses.rows.reshape(-1)[vidx], scan.row_poses)
        foreign = foreign_scan_reason(valid_pts, scan.pose, self.scanner, posed)
        if foreign:
            raise ScanError("NOT_A_LASER_SCAN", foreign)
        one_profile = single_profile_reason(valid_pts, scan.pose, float(scan.settings.direction_density),
                                            float(self.scanner.standoff_mm))

        check_deadline(deadline, "pre-processing")
        try:
            prepared = prepare_scan(scan, self.preprocess_config(), scanner=self.scanner)
        except PreprocessError as e:
            raise ScanError("NO_VALID_POINTS", f"pre-processing failed: {e}") from e
        check_deadline(deadline, "features")
        ctx = FeatureContext.from_prepared(prepared)
        try:
            X = compute_features(list(self.model.feature_names), ctx, dtype=np.float32)
        except MissingFieldError as e:
            raise ScanError("MISSING_INPUT_FIELD", str(e)) from e
        check_deadline(deadline, "inference")
        model = self.route(X, scan.pose.rotation if scan.pose is not None else None)
        model_id = str(getattr(model, "id", ""))
        # Rows with a non-finite feature get NaN from the model (and are kept out of PointNet sets).
        # U comes from the same call as the errors: a PointNet point's prediction depends on its set.
        unc_note = ""
        mv_ood = None
        tilt = None
        # the two principal curvatures when the card uses them: U per surface class, the shape domain's cells
        kappa = self._principal_curvatures(prepared, model)
        surf = (model.surface_classes(kappa) if kappa is not None and getattr(model, "by_surface", False)
                else None)
        # the scan's own noise along the normal, where the card's U takes it (a floor under σ̂)
        noise = noise_scale(prepared) if surf is not None and getattr(model, "noise_in_u", False) else None
        if getattr(model, "calibrated", False):
            up = model.predict_with_uncertainty(X, surface_class=surf, noise=noise)
            pred = np.asarray(up.errors, dtype=np.float64)
            U = np.asarray(up.U, dtype=np.float64)
            if model.card.get("domain_mv"):  # (U is widened from distance 1 on, whatever the margin)
                mv_ood = model.out_of_domain_mv(X, up.domain_distance, margin=p.domain_margin)
            # the scan's own tilt noise of its normals, where the card's along-normal allowance reads it
            an = getattr(model, "along_normal", None)
            if an is not None and an.needs_tilt and noise is not None:
                tilt = tilt_noise(prepared, offset=self.preprocess_config().grid_window)
            along = model.along_normal_rows(X, surf, noise, scan.settings, up.domain_distance, tilt=tilt)
            if along is not None:
                # d and U carried onto the measured normal, U along it from the scan's noise (judge/along_normal.py)
                pred, U = along.carry(pred, "error"), along.carry(U, "uncertainty")
        else:
            pred = np.asarray(model.predict(X), dtype=np.float64)
            U = np.full_like(pred, np.nan)
            unc_note = (f"model set {getattr(model, 'id', '?')!r} has no uncertainty calibration: "
                        "no U (NaN, flag no_uncertainty)")
        check_deadline(deadline, "flags")
        finite = np.isfinite(pred[:, 0]) & np.isfinite(pred[:, 1]) & np.isfinite(pred[:, 2])
        idx = np.asarray(prepared.index, dtype=np.int64)
        flags = base_flags(finite_xyz, outside, prepared.outlier)
        lo, hi = model.domain
        # the multivariate domain complements the per-feature range check; the shape one (a surface the
        # calibration never covered: concave, sharp) does not widen U. N·L and N·V are the features' shared
        # intermediates (already computed when the model uses Inc/ViewAng).
        shape_ood = self._shape_out_of_domain(prepared, model, kappa)
        kept_flags, cls = kept_point_flags(
            pred, U, ctx.n_dot_l(), ctx.n_dot_v(), p.grazing_incidence_deg, p.grazing_view_deg, X, lo, hi,
            p.domain_margin, prepared.normal_quality, p.normal_quality_min, p.tolerance_mm, p.decision_rule,
            mv_ood=mv_ood, shape_ood=shape_ood)
        no_u = (kept_flags & fl.FLAG_NO_UNCERTAINTY) != 0
        # d, U and the classes in the cloud's order; the invariant, whatever a stage did: no point with a
        # non-finite prediction and flags 0
        dev, unc, decisions = scatter_kept(n, idx, pred, U, kept_flags, cls, flags)

        quality = self.summarize(flags, pred, n_valid, settings_defaulted, kept is not None, n, finite=finite,
                                 U=U, u_rows=finite & ~no_u, decisions=cls[finite], note=unc_note, model_id=model_id,
                                 rescan_reason=one_profile)
        return ScanResult(deviations=dev, flags=flags, quality=quality, prepared=prepared, features=X,
                          predictions=pred, context=ctx, scan=scan, kept=kept, uncertainty=unc, row_uncertainty=U,
                          decisions=decisions, shape_out_of_domain=shape_ood, surface_class=surf, noise=noise,
                          model_id=model_id, tilt=tilt)

    def crop_rows(self, res: ScanResult, start: int, stop: int, settings_defaulted: bool = False) -> ScanResult:
        """The result of rows ``start:stop`` of an organized scan judged whole (a profile stream's chunk judged with
        context rows on both sides, so that its border rows have their neighbours): every per-point array cut to
        those rows, the kept points' arrays to the kept points in them, and the summary and verdict over them
        alone. A decimated result (``kept``) cannot be cut: ValueError."""
        from dataclasses import replace as _replace

        scan = res.scan
        if res.kept is not None or not scan.organized:
            raise ValueError("only an organized, undecimated result can be cut to rows")
        h, w = scan.shape
        if not 0 <= start < stop <= h:
            raise ValueError(f"rows {start}:{stop} outside the scan's {h}")
        lo, hi = start * w, stop * w
        prep = res.prepared
        idx = np.asarray(prep.index, dtype=np.int64)
        m = (idx >= lo) & (idx < hi)
        g = prep.geometry
        geom = type(g)(**{k: getattr(g, k)[m] for k in ("L", "V", "source_distance", "standoff", "u", "s")})
        out = np.asarray(prep.outlier, dtype=np.int64)
        prepared = _replace(prep, points=prep.points[m], normals=prep.normals[m], normal_quality=prep.normal_quality[m],
                            index=idx[m] - lo, outlier=out[(out >= lo) & (out < hi)] - lo,
                            fields={k: v[m] for k, v in prep.fields.items()}, geometry=geom, shape=(stop - start, w))
        sl = slice(lo, hi)
        def rows(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else a[start:stop]

        rp = scan.row_poses
        if rp is not None:
            rp = type(rp)(rp.positions, rp.rotations, rp.rows[start:stop])
        scan_c = _replace(scan, points=scan.points[start:stop], row_poses=rp, expected_error=rows(scan.expected_error),
                          noise_std=rows(scan.noise_std), injected_outlier=rows(scan.injected_outlier),
                          fields={k: v[start:stop] for k, v in scan.fields.items()})
        flags, pred = res.flags[sl], res.predictions[m]
        U = res.row_uncertainty[m] if res.row_uncertainty is not None else np.full_like(pred, np.nan)
        decisions = res.decisions[sl] if res.decisions is not None else None
        finite = np.isfinite(pred).all(axis=1)
        has_u = finite & np.isfinite(U).all(axis=1)
        cls = decisions[idx[m] - lo] if decisions is not None else None
        n_valid = int(np.count_nonzero(scan_c.valid_mask()))
        quality = self.summarize(flags, pred, n_valid, settings_defaulted, False, (stop - start) * w, finite=finite,
                                 U=U[has_u], decisions=cls[finite] if cls is not None else None,
                                 model_id=res.model_id)
        ctx = res.context.subset(m) if res.context is not None else None
        return _replace(res, deviations=res.deviations[sl], flags=flags, quality=quality, prepared=prepared,
                        features=res.features[m], predictions=pred, context=ctx, scan=scan_c,
                        uncertainty=None if res.uncertainty is None else res.uncertainty[sl],
                        row_uncertainty=None if res.row_uncertainty is None else res.row_uncertainty[m],
                        decisions=decisions,
                        shape_out_of_domain=None if res.shape_out_of_domain is None else res.shape_out_of_domain[m],
                        surface_class=None if res.surface_class is None else res.surface_class[m],
                        noise=None if res.noise is None else res.noise[m],
                        tilt=None if res.tilt is None else res.tilt[m])

    @staticmethod
    def _principal_curvatures(prepared: Any, model: Any) -> np.ndarray | None:
        """(M, 2) principal curvatures (κmin, κmax) 1/mm of the kept points when the model's card uses them (U per
        surface class, or a shape domain in the (κmin, κmax) plane), else None (not computed)."""
        if not (getattr(model, "by_surface", False) or getattr(model, "principal_domain", None) is not None):
            return None
        from ..preprocess.curvature import principal_curvatures

        return principal_curvatures(prepared)

    def _shape_out_of_domain(self, prepared: Any, model: Any, kappa: np.ndarray | None = None) -> np.ndarray | None:
        """(M,) bool: kept points whose shape lies outside the model's shape domain (card ``domain_shape``): their
        (κmin, κmax) cell not among the calibration's (``kappa``, when the card has ``principal`` cells), else
        their mean curvature outside its range widened by ``domain_margin``; None when the card has none. NaN
        curvature (unorganized scan, scan border) is not flagged."""
        grid = getattr(model, "principal_domain", None)
        if grid is not None and kappa is not None:
            return out_of_principal_domain(kappa, *grid)
        dom = getattr(model, "shape_domain", None)
        if dom is None:
            return None
        from ..preprocess.curvature import mean_curvature

        lo, hi, radius = dom
        m = self.params.domain_margin * (hi - lo)
        c = mean_curvature(prepared, radius)
        with np.errstate(invalid="ignore"):
            return (c < lo - m) | (c > hi + m)

    def summarize(self, flags: np.ndarray, pred: np.ndarray, n_valid: int, settings_defaulted: bool,
                  decimated: bool, n_received: int, finite: np.ndarray | None = None, U: np.ndarray | None = None,
                  decisions: np.ndarray | None = None, note: str = "", model_id: str | None = None,
                  rescan_reason: str = "", u_rows: np.ndarray | None = None) -> dict[str, Any]:
        """Quality summary (mm): counts, per-flag counts, mean / p95 |error| and U per axis, decision class counts,
        verdict and its reason.

        ``pred`` (M, 3) mm: the predictions the error statistics are over, only its rows ``finite`` (bool (M,))
        when given; ``U`` (Q, 3): finite U of the predicted points that have one, or with ``u_rows`` (bool (Q,))
        those of its rows (the same figures, without gathering them first); ``decisions`` (P,): the class of
        each finite prediction; ``note``: added to the message (why there is no U); ``model_id``: the model set
        that judged (default: the primary's id); ``rescan_reason``: a reason the scan is RESCAN at best, whatever
        its flags say (a single profile: its normals are not those of a surface), first in the message. Compiled
        one-pass statistics (xmetro_ros.judge.scan_stats), the same numbers as numpy's ``count_nonzero`` /
        ``flag_counts`` / ``mean(axis=0)`` / ``percentile(95, axis=0)`` (tested)."""
        from .scan_stats import abs_error_stats, flag_tally

        n_flagged_all, counts = flag_tally(flags, fl.FLAG_BITS)
        # One definition of each figure, the verdict's: over the VALID points (not the empty grid cells, which all
        # carry INVALID_POINT or OUT_OF_VOLUME and are counted in flag_counts). Usable = valid and without a quality
        # bit; decision bits do not make a point unusable (flags module docstring). Flagged = valid with any flag.
        n_flagged = n_flagged_all - (n_received - n_valid)
        n_quality = int(np.count_nonzero(np.asarray(flags) & fl.QUALITY_BITS))
        n_usable = n_received - n_quality
        dec_counts = (np.bincount(np.asarray(decisions, dtype=np.int64), minlength=3)[:3] if decisions is not None
                      and len(decisions) else np.zeros(3, dtype=np.int64))
        code, reason = fl.verdict(n_valid, n_usable, n_quality - (n_received - n_valid),
                                  int(dec_counts[fl.NON_CONFORMING]), self.params.thresholds,
                                  settings_defaulted=settings_defaulted, decimated=decimated,
                                  n_undecided=int(dec_counts[fl.UNDECIDED]),
                                  # which flags: a user acts differently on grazing points (turn the head) and on
                                  # unseen shapes (a model that knows them)
                                  flags_why=fl.flag_breakdown(counts, n_valid))
        if rescan_reason:
            code, reason = max(code, fl.VERDICT_RESCAN), f"{rescan_reason}; {reason}"
        mean, p95 = abs_error_stats(pred, finite, 95.0)
        Ua = np.empty((0, 3)) if U is None else np.asarray(U, dtype=np.float64)
        # U >= 0: the statistics of |U| are those of U (numpy's mean and linear percentile, by selection)
        n_u = len(Ua) if u_rows is None else int(np.count_nonzero(u_rows))
        u_mean, u_p95 = abs_error_stats(Ua, u_rows, 95.0) if n_u else (np.full(3, np.nan), np.full(3, np.nan))
        notes = [reason]
        if note:
            notes.append(note)
        if settings_defaulted:
            notes.append("no valid ScannerSettings at or before the scan: configured defaults used")
        if decimated:
            notes.append(f"cloud decimated to {n_received} points (max_points)")
        return {
            "verdict": code,
            "verdict_name": fl.VERDICT_NAMES[code],
            "error_code": "NONE",
            "message": "; ".join(dict.fromkeys(notes)),
            "points_received": n_received,
            "points_valid": n_valid,
            "points_flagged": n_flagged,
            "flag_names": list(fl.FLAG_NAMES),
            "flag_counts": counts,
            "mean_abs_error_mm": [float(x) for x in mean],
            "p95_abs_error_mm": [float(x) for x in p95],
            "mean_uncertainty_mm": [float(x) for x in u_mean],
            "p95_uncertainty_mm": [float(x) for x in u_p95],
            "decision_rule": self.params.decision_rule,
            "decision_names": list(fl.DECISION_NAMES),
            "decision_counts": [int(c) for c in dec_counts],
            "usable_fraction": n_usable / n_valid if n_valid else 0.0,
            "settings_defaulted": bool(settings_defaulted),
            "decimated": bool(decimated),
            "model_id": getattr(self.model, "id", "") if model_id is None else model_id,
        }
