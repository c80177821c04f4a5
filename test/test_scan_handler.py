"""ScanHandler (the one processing path), the point cap, flags and verdict rules — no DDS."""

from __future__ import annotations

import os
from dataclasses import replace

import numpy as np
import pytest

from xmetro_ros.judge import flags as fl
from xmetro_ros.judge.inference import ModelSet
from xmetro_ros.judge.scan_handler import HandlerParams, ScanError, ScanHandler, cap_points, decimation_index
from xmetro_ros.scan.artifacts import Sphere
from xmetro_ros.scan.scan import Scan
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings
from xmetro_ros.sim import simulate_scan


@pytest.fixture(scope="module")
def handler() -> ScanHandler:
    model = ModelSet.load(os.environ.get("XMETRO_TEST_MODEL_DIR") or None)
    return ScanHandler(model, ScannerModel.load(), HandlerParams())


@pytest.fixture(scope="module")
def scan() -> Scan:
    return simulate_scan(Sphere(17.5, np.zeros(3)), ScanSettings(6.0, 3.0, 0.5), seed=1)


def test_process_organized_and_unorganized(handler, scan):
    res = handler.process(scan)
    n = int(np.prod(scan.shape))
    assert res.deviations.shape == (n, 3) and res.flags.shape == (n,) and res.flags.dtype == np.uint16
    valid = scan.valid_mask()
    assert np.isnan(res.deviations[~valid]).all()
    assert np.all(res.flags[~valid] & fl.FLAG_INVALID_POINT)
    assert np.count_nonzero(res.flags & fl.FLAG_INVALID_POINT) >= n - int(valid.sum())
    # deviations of kept points are the model's prediction on the model's features
    np.testing.assert_array_equal(res.deviations[res.prepared.index], res.predictions)
    np.testing.assert_array_equal(res.predictions, handler.model.predict(res.features))
    assert res.features.dtype == np.float32 and res.features.shape[1] == len(handler.model.feature_names)
    outl = np.asarray(res.prepared.outlier)
    assert np.all(res.flags[outl] & fl.FLAG_OUTLIER) and np.isnan(res.deviations[outl]).all()
    q = res.quality
    assert q["points_received"] == n and q["points_valid"] == int(valid.sum())
    assert q["flag_counts"] == fl.flag_counts(res.flags)
    # Over the valid points, the verdict's figure (issue 27: one definition); flagged ≤ valid.
    assert q["usable_fraction"] == pytest.approx(np.count_nonzero((res.flags & fl.QUALITY_BITS) == 0) / valid.sum())
    assert q["points_flagged"] == int(np.count_nonzero(res.flags.reshape(-1)[valid.reshape(-1)])) <= q["points_valid"]
    assert q["verdict_name"] == fl.VERDICT_NAMES[q["verdict"]]
    # the same scan unorganized: same points processed (open3d path), one deviation per point
    pts, fields, _idx = scan.flat()
    flat = Scan(points=pts, settings=scan.settings, pose=scan.pose, scanner_id=scan.scanner_id, fields=fields)
    r2 = handler.process(flat)
    assert r2.deviations.shape == (len(pts), 3) and np.isfinite(r2.deviations).any(axis=1).mean() > 0.8


def test_flag_thresholds_follow_parameters(handler, scan):
    base = handler.params
    try:
        handler.params = replace(base, tolerance_mm=1e-9)
        r = handler.process(scan)
        pred_ok = np.zeros(len(r.flags), bool)
        pred_ok[r.prepared.index] = np.isfinite(r.predictions).all(axis=1)
        assert np.array_equal((r.flags & fl.FLAG_OVER_TOLERANCE) > 0, pred_ok)
        assert r.quality["verdict"] == fl.VERDICT_RESCAN
        handler.params = replace(base, tolerance_mm=1e9, grazing_incidence_deg=90.0, grazing_view_deg=90.0,
                                 normal_quality_min=0.0, domain_margin=1e6,
                                 thresholds=fl.VerdictThresholds(warn_flagged_fraction=1.0))
        r = handler.process(scan)
        assert not np.any(r.flags & (fl.FLAG_OVER_TOLERANCE | fl.FLAG_OUT_OF_DOMAIN | fl.FLAG_UNRELIABLE_NORMAL))
        handler.params = replace(base, normal_quality_min=1.01)
        r = handler.process(scan)
        kept = np.zeros(len(r.flags), bool)
        kept[r.prepared.index] = True
        assert np.all(r.flags[kept] & fl.FLAG_UNRELIABLE_NORMAL)
        r = handler.process(scan, settings_defaulted=True)
        assert r.quality["settings_defaulted"] and r.quality["verdict"] >= fl.VERDICT_WARN
    finally:
        handler.params = base


def test_out_of_domain_says_which_check_and_only_the_multivariate_one_widens_u(handler):
    # A narrowed margin (negative: inside the training range) so that the feature and multivariate checks flag
    # points; the settings in the middle of the training range (6 / 3 lie on its edge). A Ø20 sphere: curved by
    # 0.1 /mm both ways, most of its (κmin, κmax) lie where no calibration shape was (the shipped card's shape
    # check has no margin).
    scan = simulate_scan(Sphere(10.0, np.zeros(3)), ScanSettings(10.0, 4.0, 0.5), seed=2)
    base = handler.params
    try:
        handler.params = replace(base, domain_margin=-0.1)
        r = handler.process(scan)
    finally:
        handler.params = base
    model = handler.model
    assert r.model_id == model.id
    kf = r.flags[r.prepared.index]
    bit = {b: (kf & b) > 0 for b in (fl.FLAG_OUT_OF_DOMAIN, fl.FLAG_DOMAIN_FEATURES, fl.FLAG_DOMAIN_MULTIVARIATE,
                                     fl.FLAG_DOMAIN_SHAPE)}
    # each reason bit is its own check, recomputed here
    feat = (fl.domain_flags(r.features, *model.domain, -0.1) & fl.FLAG_DOMAIN_FEATURES) > 0
    dist = model.domain_distance(r.features)
    np.testing.assert_array_equal(bit[fl.FLAG_DOMAIN_FEATURES], feat)
    np.testing.assert_array_equal(bit[fl.FLAG_DOMAIN_MULTIVARIATE], model.out_of_domain_mv(r.features, dist, -0.1))
    np.testing.assert_array_equal(bit[fl.FLAG_DOMAIN_SHAPE], r.shape_out_of_domain)
    # OUT_OF_DOMAIN is set exactly where some reason is, and every reason occurs here
    reasons = bit[fl.FLAG_DOMAIN_FEATURES] | bit[fl.FLAG_DOMAIN_MULTIVARIATE] | bit[fl.FLAG_DOMAIN_SHAPE]
    np.testing.assert_array_equal(bit[fl.FLAG_OUT_OF_DOMAIN], reasons)
    for b in (fl.FLAG_DOMAIN_FEATURES, fl.FLAG_DOMAIN_MULTIVARIATE, fl.FLAG_DOMAIN_SHAPE):
        assert 0 < bit[b].sum() < len(kf), fl.FLAG_NAMES[fl.FLAG_BITS.index(b)]
    # What each does to U: the published U is the unwidened one × max(1, distance). The multivariate bit is
    # distance > 1 + margin (checked above), so with a margin >= 0 its points are widened; a point flagged for its
    # features or its shape alone may lie at a distance <= 1 and then keeps its U.
    _err, sig = model.predict_with_sigma(r.features)
    model.domain_distance = lambda X: np.full(len(X), np.nan)  # NaN distance: no widening (this instance only)
    try:
        U0, _ = model._expand(sig, r.features, r.surface_class, r.noise)
    finally:
        del model.domain_distance
    far = dist > 1.0
    np.testing.assert_allclose(r.row_uncertainty[far], U0[far] * dist[far, None], rtol=1e-9)
    np.testing.assert_array_equal(r.row_uncertainty[~far], U0[~far])
    assert (bit[fl.FLAG_DOMAIN_SHAPE] & ~far).any() and (bit[fl.FLAG_DOMAIN_FEATURES] & ~far).any()
    q = r.quality["flag_counts"]
    assert q[fl.FLAG_BITS.index(fl.FLAG_DOMAIN_SHAPE)] == int(bit[fl.FLAG_DOMAIN_SHAPE].sum())
    # the verdict's message says which flags, and why out of domain
    assert r.quality["verdict"] >= fl.VERDICT_WARN
    assert "(flags: out_of_domain " in r.quality["message"] and "domain_features" in r.quality["message"]


def test_flag_breakdown_names_the_flags_behind_a_verdict():
    counts = [0] * len(fl.FLAG_BITS)

    def put(bit: int, n: int) -> None:
        counts[fl.FLAG_BITS.index(bit)] = n

    put(fl.FLAG_OUT_OF_DOMAIN, 600)
    put(fl.FLAG_DOMAIN_SHAPE, 550)
    put(fl.FLAG_DOMAIN_MULTIVARIATE, 100)
    put(fl.FLAG_DOMAIN_FEATURES, 3)
    put(fl.FLAG_GRAZING_VIEW, 80)
    put(fl.FLAG_OUTLIER, 10)  # 1 %: under the 5 % shown
    put(fl.FLAG_INVALID_POINT, 5000)  # empty cells: never shown
    put(fl.FLAG_UNDECIDED, 900)  # a decision bit, not a quality bit
    why = fl.flag_breakdown(counts, 1000)
    assert why == ("out_of_domain 60 % (domain_shape 55 %, domain_multivariate 10 %, domain_features <1 %), "
                   "grazing_view 8 %")
    assert fl.flag_breakdown(counts, 0) == "" and fl.flag_breakdown([0] * len(fl.FLAG_BITS), 1000) == ""
    code, msg = fl.verdict(1000, 340, 660, 0, fl.VerdictThresholds(), flags_why=why)
    assert code == fl.VERDICT_RESCAN and msg == f"usable fraction 0.340 < 0.5 (flags: {why})"
    code, msg = fl.verdict(1000, 700, 300, 0, fl.VerdictThresholds(), settings_defaulted=True, flags_why=why)
    assert code == fl.VERDICT_WARN and msg == f"flagged fraction 0.300 > 0.25 (flags: {why}); settings defaulted"


def test_domain_and_angle_flags_unit():
    X = np.array([[0.0, 1.0], [2.0, 1.0], [0.5, -0.2]], np.float32)
    f = fl.domain_flags(X, np.array([0.0, 0.0]), np.array([1.0, 1.0]), margin=0.1)
    ood = fl.FLAG_OUT_OF_DOMAIN | fl.FLAG_DOMAIN_FEATURES
    assert f.tolist() == [0, ood, ood]
    n = np.array([[0, 0, 1.0], [0, 0, 1.0], [1.0, 0, 0]])
    lv = np.array([[0, 0, 1.0], [np.sin(np.radians(80)), 0, np.cos(np.radians(80))], [0, 0, 1.0]])
    a = fl.angle_flags(n, lv, lv, 75.0, 85.0)
    assert a.tolist() == [0, fl.FLAG_GRAZING_INCIDENCE, fl.FLAG_GRAZING_INCIDENCE | fl.FLAG_GRAZING_VIEW]


def test_verdict_rules():
    th = fl.VerdictThresholds(warn_flagged_fraction=0.25, rescan_usable_fraction=0.5,
                              rescan_over_tolerance_fraction=0.05, min_valid_points=100)
    assert fl.verdict(1000, 1000, 0, 0, th)[0] == fl.VERDICT_OK
    assert fl.verdict(1000, 700, 300, 0, th)[0] == fl.VERDICT_WARN
    assert fl.verdict(1000, 750, 250, 0, th)[0] == fl.VERDICT_OK  # not strictly over
    assert fl.verdict(1000, 490, 510, 0, th)[0] == fl.VERDICT_RESCAN
    assert fl.verdict(1000, 900, 100, 60, th)[0] == fl.VERDICT_RESCAN
    assert fl.verdict(99, 99, 0, 0, th)[0] == fl.VERDICT_RESCAN
    assert fl.verdict(1000, 1000, 0, 0, th, settings_defaulted=True) == (fl.VERDICT_WARN, "settings defaulted")
    assert fl.verdict(1000, 1000, 0, 0, th, decimated=True)[0] == fl.VERDICT_WARN


def test_errors_and_point_cap(handler, scan):
    nan = replace(scan, points=np.full_like(scan.points, np.nan))
    with pytest.raises(ScanError) as e:
        handler.process(nan)
    assert e.value.code == "NO_VALID_POINTS"
    with pytest.raises(ScanError) as e:
        handler.process(replace(scan, settings=ScanSettings(6.0, 3.0, -1.0)))
    assert e.value.code == "INVALID_SETTINGS" and "exposure_ms" in str(e.value)
    with pytest.raises(ScanError) as e:
        ScanHandler(None, handler.scanner).process(scan)
    assert e.value.code == "MODEL_UNAVAILABLE"
    n = int(np.prod(scan.shape))
    with pytest.raises(ScanError) as e:
        cap_points(scan, n - 1, "reject")
    assert e.value.code == "TOO_MANY_POINTS"
    small, keep = cap_points(scan, n // 3, "decimate")
    assert len(keep) <= n // 3 and not small.organized and len(small.points) == len(keep)
    np.testing.assert_array_equal(small.points, scan.points.reshape(-1, 3)[keep])
    assert cap_points(scan, n, "reject")[1] is None
    assert decimation_index(10, 3).tolist() == [0, 4, 8]
    old = handler.params
    try:
        handler.params = replace(old, max_points=n // 3, cloud_overflow="decimate")
        r = handler.process(scan)
        assert r.quality["decimated"] and r.quality["verdict"] >= fl.VERDICT_WARN and len(r.flags) == len(keep)
    finally:
        handler.params = old


def test_out_of_volume_points_flagged_and_every_point_accounted(handler, scan):
    """Finite but non-physical coordinates (3e41 mm = 3e38 m, and just past the working volume) are flagged
    OUT_OF_VOLUME with no prediction; the other points are judged as without them; no NaN prediction with flags 0."""
    pts = scan.points.reshape(-1, 3).copy()
    fin = np.flatnonzero(np.isfinite(pts).all(axis=1))
    absurd = fin[::3]
    pts[absurd[::2]] = 3e41
    pts[absurd[1::2], 0] = handler.params.working_volume_mm * 1.001  # one coordinate just outside
    bad = replace(scan, points=pts.reshape(scan.points.shape))
    res = handler.process(bad)
    assert np.all(res.flags[absurd] & fl.FLAG_OUT_OF_VOLUME) and np.isnan(res.deviations[absurd]).all()
    assert not np.any(res.flags[absurd] & fl.FLAG_INVALID_POINT)  # finite: the flag says which case it is
    assert res.quality["points_valid"] == len(fin) - len(absurd)
    assert res.quality["flag_counts"][fl.FLAG_BITS.index(fl.FLAG_OUT_OF_VOLUME)] == len(absurd)
    silent = ~np.isfinite(res.deviations).all(axis=1) & (res.flags == 0)
    assert not silent.any()
    # the rest is judged exactly as if those points had no return
    nan_pts = pts.copy()
    nan_pts[absurd] = np.nan
    ref = handler.process(replace(scan, points=nan_pts.reshape(scan.points.shape)))
    np.testing.assert_array_equal(res.deviations, ref.deviations)
    others = np.setdiff1d(np.arange(len(pts)), absurd)
    np.testing.assert_array_equal(res.flags[others], ref.flags[others])
    assert np.isfinite(res.quality["mean_abs_error_mm"]).all()
    # a working volume that excludes every point: NO_VALID_POINTS, saying why
    handler_small = ScanHandler(handler.model, handler.scanner, replace(handler.params, working_volume_mm=1e-3))
    with pytest.raises(ScanError) as e:
        handler_small.process(scan)
    assert e.value.code == "NO_VALID_POINTS" and "working volume" in str(e.value)


def test_deadline_abandons_between_stages(handler, scan):
    import time

    with pytest.raises(ScanError) as e:
        handler.process(scan, deadline=time.monotonic() - 1.0)
    assert e.value.code == "TIMEOUT" and "max_processing_time" in str(e.value)
    assert handler.process(scan, deadline=time.monotonic() + 600.0).quality["error_code"] == "NONE"


def test_a_single_profile_is_never_judged_a_good_scan(handler):
    """Issue 24: one profile of a driver sent as a cloud (the middle row of a 55 mm sphere scan at 15/5/2, its own
    settings and pose) has no neighbours across the scan direction: judged RESCAN at best, and the message says why;
    the scan it came from, and a narrow strip of 5 rows, are not called a single profile."""
    from xmetro_ros.judge.scan_handler import single_profile_reason

    full = simulate_scan(Sphere(27.5, np.zeros(3)), ScanSettings(15.0, 5.0, 2.0), seed=3)
    mid = full.shape[0] // 2
    row = Scan(points=full.points[mid:mid + 1], settings=full.settings, pose=full.pose, scanner_id=full.scanner_id,
               fields={k: v[mid:mid + 1] for k, v in full.fields.items()})
    q = handler.process(row).quality
    assert q["verdict"] == fl.VERDICT_RESCAN and "single laser-line profile" in q["message"], q["message"]
    assert "single laser-line profile" not in handler.process(full).quality["message"]
    strip = full.points[mid - 2:mid + 3].reshape(-1, 3)
    strip = strip[np.isfinite(strip).all(axis=1)]
    assert single_profile_reason(strip, full.pose, full.settings.direction_density, 90.0) == ""
    one = full.points[mid].reshape(-1, 3)
    assert single_profile_reason(one[np.isfinite(one).all(axis=1)], full.pose, full.settings.direction_density, 90.0)
