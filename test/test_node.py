"""xmetro_node end to end over localhost DDS (in-process node, NodeSpinner): outputs equal the offline ScanHandler,
flags / verdict follow their thresholds, both services, every bad input, live parameters, /diagnostics.

One node start-up for the whole module (the checks run in order in one test function per area, sharing it).
The node uses the shipped default model; XMETRO_TEST_MODEL_DIR=<model set dir> runs the same checks with another."""

from __future__ import annotations

import os

import numpy as np
import pytest
from rcl_interfaces.msg import Log
from rclpy.parameter import Parameter
from sensor_msgs.msg import PointCloud2, PointField
from test_node_helpers import (
    TIMEOUT,
    NodeClient,
    bigendian_copy,
    cloud_of,
    raw_cloud,
    settings_msg,
    sim_scan,
    stamp_ns_of,
)

from xmetro_ros.judge import flags as fl
from xmetro_ros.judge.inference import ModelSet
from xmetro_ros.judge.scan_handler import ScanHandler
from xmetro_ros.msg import ScanQuality
from xmetro_ros.ros.cloud import xyz_fields
from xmetro_ros.ros.convert import cloud_to_scan, ns_to_stamp
from xmetro_ros.ros.node import XmetroNode
from xmetro_ros.ros.params import handler_params
from xmetro_ros.ros.rclpy_util import NodeSpinner, call_service, wait_for
from xmetro_ros.scan.scanner import ScannerModel
from xmetro_ros.srv import Explain, RecommendSettings

S = 1_000_000_000  # ns per second
ERROR = 2  # DiagnosticStatus.ERROR
WARN = 1


@pytest.fixture(scope="module")
def rig():
    overrides = [Parameter("min_valid_points", value=50), Parameter("explain_max_points", value=500),
                 Parameter("model_dir", value=os.environ.get("XMETRO_TEST_MODEL_DIR", ""))]
    node_sp = NodeSpinner(lambda ctx: XmetroNode(context=ctx, parameter_overrides=overrides))
    cli_sp = NodeSpinner(lambda ctx: __import__("rclpy.node", fromlist=["Node"]).Node("xmetro_tester", context=ctx))
    client = NodeClient(cli_sp.node)
    try:
        client.wait_matched(node_sp.node)
        yield node_sp.node, client, cli_sp.node
    finally:
        cli_sp.close()
        node_sp.close()


def _offline(node: XmetroNode, msg, settings_scan, defaulted=False):
    """The offline pipeline on the same cloud: ScanHandler on cloud_to_scan with the node's parameters."""
    scan = cloud_to_scan(msg, settings_scan.settings, settings_scan.pose, settings_scan.scanner_id)
    # Same ONNX Runtime thread count as the node: tree ensembles sum in a thread-dependent order (last-bit changes).
    model = ModelSet.load(node.core.values["model_dir"] or None, threads=node.core.values["inference_threads"])
    handler = ScanHandler(model, ScannerModel.load(),
                          handler_params(node.core.values))
    return handler.process(scan, settings_defaulted=defaulted)


def _arrays(cloud) -> dict[str, np.ndarray]:
    names = [f.name for f in cloud.fields if f.name not in ("x", "y", "z")]
    xyz, extra = xyz_fields(cloud, names)
    return {"xyz": np.asarray(xyz), **{k: np.asarray(v) for k, v in extra.items()}}


def _set(node: XmetroNode, **kw) -> list:
    return node.set_parameters([Parameter(k, value=v) for k, v in kw.items()])


def test_outputs_match_offline_and_flags(rig):
    node, client, tester = rig
    # no scan judged yet: both services refuse cleanly
    r = call_service(tester.create_client(Explain, "/xmetro_node/explain"), Explain.Request(), timeout=TIMEOUT)
    assert not r.success and "no scan judged yet" in r.message
    r = call_service(tester.create_client(RecommendSettings, "/xmetro_node/recommend_settings"),
                     RecommendSettings.Request(), timeout=TIMEOUT)
    assert not r.success and "no scan judged yet" in r.message
    base = sim_scan(10 * S)
    client.pub_settings.publish(settings_msg(base, 5 * S))
    assert wait_for(lambda: node.core.settings_count >= 1, TIMEOUT)

    msg = cloud_of(base)
    q, dev, corr = client.send(msg)
    assert q.error_code == ScanQuality.ERROR_NONE, q.message
    assert not q.settings_defaulted
    assert q.model_id == node.core.model_id != ""
    assert (dev.height, dev.width) == (msg.height, msg.width)
    assert [f.name for f in dev.fields] == ["x", "y", "z", "dx", "dy", "dz", "dnorm", "ux", "uy", "uz", "flags"]
    assert dev.fields[-1].datatype == PointField.UINT16

    res = _offline(node, msg, base)
    d = _arrays(dev)
    # published d = measured − nominal: the model's target (nominal − measured) with its sign flipped, bit for bit
    expect_m = (-res.deviations * 1e-3).astype(np.float32)
    np.testing.assert_array_equal(np.column_stack([d["dx"], d["dy"], d["dz"]]), expect_m)
    np.testing.assert_array_equal(d["flags"].astype(np.uint16), res.flags)
    # invalid (NaN) grid cells are flagged and have no deviation
    nan = ~np.isfinite(base.points.reshape(-1, 3)).all(axis=1)
    assert nan.any()
    assert np.all(res.flags[nan] & fl.FLAG_INVALID_POINT)
    assert np.isnan(d["dx"][nan]).all()
    # quality summary = the offline one (metres)
    assert q.points_received == res.quality["points_received"] == msg.width * msg.height
    assert q.points_valid == res.quality["points_valid"] == int((~nan).sum())
    assert list(q.flag_counts) == res.quality["flag_counts"] == fl.flag_counts(res.flags)
    assert list(q.flag_names) == list(fl.FLAG_NAMES)
    np.testing.assert_allclose(q.mean_abs_error, np.array(res.quality["mean_abs_error_mm"]) * 1e-3, rtol=1e-12)
    assert q.verdict == res.quality["verdict"]
    assert q.processing_latency > 0

    # corrected: same fields, x, y, z − d (measured minus the published deviation; unpredicted points unchanged)
    assert [f.name for f in corr.fields] == [f.name for f in msg.fields]
    c, m = _arrays(corr), _arrays(msg)
    np.testing.assert_array_equal(d["xyz"], m["xyz"])  # deviations carry the points exactly as received
    pub = np.nan_to_num(np.column_stack([d["dx"], d["dy"], d["dz"]]))
    np.testing.assert_allclose(c["xyz"], m["xyz"] - pub, rtol=0, atol=1e-7, equal_nan=True)
    np.testing.assert_array_equal(c["intensity"], m["intensity"])

    # flags follow their thresholds: recompute them from the judged scan
    dn = np.linalg.norm(res.predictions, axis=1)
    over = np.zeros(len(res.flags), bool)
    over[res.prepared.index] = dn > node.core.handler.params.tolerance_mm
    assert np.array_equal((res.flags & fl.FLAG_OVER_TOLERANCE) > 0, over)
    g = res.prepared.geometry
    cos_i = np.einsum("ij,ij->i", res.prepared.normals, g.L)
    graz = np.zeros(len(res.flags), bool)
    graz[res.prepared.index] = cos_i < np.cos(np.radians(75.0))
    assert np.array_equal((res.flags & fl.FLAG_GRAZING_INCIDENCE) > 0, graz)

    # live thresholds: a tiny tolerance → every predicted point over tolerance → RESCAN (simple acceptance: every
    # such point non-conforming); a huge one → none
    assert all(r.successful for r in _set(node, tolerance=1e-7, decision_rule="simple"))
    q2, _dev2, _ = client.send(cloud_of(sim_scan(11 * S)))
    assert q2.verdict == ScanQuality.VERDICT_RESCAN
    assert "fraction" in q2.message
    assert q2.flag_counts[fl.FLAG_BITS.index(fl.FLAG_OVER_TOLERANCE)] >= 0.9 * q2.points_valid
    assert all(r.successful for r in _set(node, tolerance=0.1, grazing_incidence_deg=90.0, grazing_view_deg=90.0,
                                          warn_flagged_fraction=1.0, rescan_usable_fraction=0.0,
                                          normal_quality_min=0.0, domain_margin=10.0))
    q3, _, _ = client.send(cloud_of(sim_scan(12 * S)))
    assert q3.flag_counts[fl.FLAG_BITS.index(fl.FLAG_OVER_TOLERANCE)] == 0
    assert q3.verdict == ScanQuality.VERDICT_OK, q3.message
    # rejected changes: bad choice, read-only parameter
    assert not _set(node, cloud_overflow="explode")[0].successful
    assert not _set(node, model_dir="/elsewhere")[0].successful
    assert node.get_parameter("cloud_overflow").value == "reject"
    _set(node, tolerance=0.0001, decision_rule="guard_banded", grazing_incidence_deg=75.0, grazing_view_deg=75.0,
         warn_flagged_fraction=0.25,
         rescan_usable_fraction=0.5, normal_quality_min=0.3, domain_margin=0.05)

    # big-endian data is decoded, not rejected: same deviations as the little-endian cloud
    be = bigendian_copy(cloud_of(sim_scan(13 * S)))
    le_res = _offline(node, cloud_of(sim_scan(13 * S)), base)
    qb, devb, corrb = client.send(be)
    assert qb.error_code == ScanQuality.ERROR_NONE, qb.message
    db = _arrays(devb)
    np.testing.assert_array_equal(db["dx"], (-le_res.deviations[:, 0] * 1e-3).astype(np.float32))
    assert corrb.is_bigendian


def test_bad_inputs_each_reported_and_node_keeps_running(rig):
    node, client, _ = rig
    base = sim_scan(20 * S)
    client.pub_settings.publish(settings_msg(base, 19 * S))
    assert wait_for(lambda: node.core.settings_for(20 * S) is not None
                    and node.core.settings_for(20 * S).stamp_ns == 19 * S, TIMEOUT)
    t = [21 * S]

    def good() -> None:
        t[0] += 1000
        # sent again after 10 s without an answer: a scan lost in transport on a loaded machine (the node counts
        # it lost) is not the node failing; a node that stopped answering still fails the 30 s bound
        q, dev, _ = client.send(cloud_of(sim_scan(t[0])), resend_every=10.0)
        assert q.error_code == ScanQuality.ERROR_NONE and q.verdict != ScanQuality.VERDICT_ERROR, q.message
        assert dev is not None

    def bad(msg, code: int, text: str, then_good: bool = True) -> None:
        mark, log_mark = client.diag_mark(), client.log_mark()
        q, _, _ = client.send(msg, outputs=False)
        assert q.verdict == ScanQuality.VERDICT_ERROR, q.message
        assert q.error_code == code, (q.error_code, q.message)
        assert text in q.message, q.message
        diag = client.wait_diag_level(ERROR, mark)
        assert text in diag.status[0].message, diag.status[0].message
        client.wait_log(Log.ERROR, text, log_mark)  # the node logs it, at ERROR, with the reason
        if then_good:
            good()  # the next good scan is processed normally

    def stamp() -> int:
        t[0] += 1000
        return t[0]

    f32, f64, i32 = PointField.FLOAT32, PointField.FLOAT64, PointField.INT32
    xyz = [("x", 0, f32), ("y", 4, f32), ("z", 8, f32)]
    pts = np.tile(np.array([[0.0, 0.0, 0.01]], np.float32), (60, 1)) + \
        np.random.default_rng(0).normal(0, 0.001, (60, 3)).astype(np.float32)
    good()
    bad(raw_cloud(xyz, 12, 0, b"", stamp_ns=stamp()), ScanQuality.ERROR_EMPTY_CLOUD, "no points")
    bad(raw_cloud(xyz, 12, 60, pts.tobytes()[:-12], stamp_ns=stamp()), ScanQuality.ERROR_BAD_LAYOUT, "bytes")
    bad(raw_cloud(xyz, 12, 60, pts.tobytes(), stamp_ns=stamp(), row_step=100), ScanQuality.ERROR_BAD_LAYOUT,
        "row_step")
    bad(raw_cloud(xyz, 8, 60, bytes(8 * 60), stamp_ns=stamp()), ScanQuality.ERROR_BAD_LAYOUT, "point_step")
    bad(raw_cloud(xyz[:2], 12, 60, pts.tobytes(), stamp_ns=stamp()), ScanQuality.ERROR_MISSING_FIELD, "'z'")
    bad(raw_cloud([("x", 0, i32), ("y", 4, f32), ("z", 8, f32)], 12, 60, pts.tobytes(), stamp_ns=stamp()),
        ScanQuality.ERROR_MISSING_FIELD, "'x'")
    bad(raw_cloud([*xyz, ("y", 12, f32)], 16, 60, bytes(16 * 60), stamp_ns=stamp()),
        ScanQuality.ERROR_DUPLICATE_FIELD, "duplicate")
    nan = np.full((60, 3), np.nan, np.float32)
    bad(raw_cloud(xyz, 12, 60, nan.tobytes(), stamp_ns=stamp()), ScanQuality.ERROR_NO_VALID_POINTS, "NaN")
    inf = pts.copy()
    inf[:, 2] = np.inf
    bad(raw_cloud(xyz, 12, 60, inf.tobytes(), stamp_ns=stamp()), ScanQuality.ERROR_NO_VALID_POINTS, "Inf")
    # float64 x, y, z are fine (a few points only → processed, verdict RESCAN for too few points)
    q, _, _ = client.send(raw_cloud([("x", 0, f64), ("y", 8, f64), ("z", 16, f64)], 24, 40,
                                    pts[:40].astype(np.float64).tobytes(), stamp_ns=stamp()))
    assert q.error_code == ScanQuality.ERROR_NONE and q.verdict == ScanQuality.VERDICT_RESCAN, q.message

    # NaN / Inf points inside a good cloud: flagged INVALID_POINT, the rest processed
    sc = sim_scan(stamp())
    pts_nan = sc.points.copy()
    fin = np.argwhere(np.isfinite(pts_nan).all(axis=2))
    pts_nan[tuple(fin[0])] = [np.inf, 0.0, 0.0]
    sc.points = pts_nan
    q, dev, _ = client.send(cloud_of(sc))
    assert q.error_code == ScanQuality.ERROR_NONE
    flags = _arrays(dev)["flags"].astype(np.uint16).reshape(sc.shape)
    assert flags[tuple(fin[0])] & fl.FLAG_INVALID_POINT
    assert q.flag_counts[fl.FLAG_BITS.index(fl.FLAG_INVALID_POINT)] == q.points_received - q.points_valid

    # too many points: reject, then decimate (WARN, at most max_points points out)
    _set(node, max_points=5000)
    big = cloud_of(sim_scan(stamp()))
    bad(big, ScanQuality.ERROR_TOO_MANY_POINTS, "max_points", then_good=False)
    _set(node, cloud_overflow="decimate")
    big.header.stamp = ns_to_stamp(stamp())
    q, dev, corr = client.send(big)
    assert q.error_code == ScanQuality.ERROR_NONE and q.verdict >= ScanQuality.VERDICT_WARN
    assert "decimated" in q.message
    assert dev.width * dev.height <= 5000 and corr.width == dev.width and q.points_received == dev.width
    _set(node, max_points=2_000_000, cloud_overflow="reject")

    # settings out of range (negative exposure, zero density), then frame mismatch
    for si in ({"exposure_time": -0.001}, {"lateral_density": 0.0}):
        s_t = stamp()
        client.pub_settings.publish(settings_msg(base, s_t, **si))
        assert wait_for(lambda s_t=s_t: node.core.settings_for(s_t + 1) is not None
                        and node.core.settings_for(s_t + 1).stamp_ns == s_t, TIMEOUT)
        bad(cloud_of(sim_scan(stamp())), ScanQuality.ERROR_INVALID_SETTINGS, "invalid", then_good=False)
        # the good scans that follow need valid settings again
        v_t = stamp()
        client.pub_settings.publish(settings_msg(base, v_t))
        assert wait_for(lambda v_t=v_t: getattr(node.core.settings_for(v_t + 1), 'stamp_ns', None) == v_t, TIMEOUT)
        good()
    f_t = stamp()
    client.pub_settings.publish(settings_msg(base, f_t, frame_id="elsewhere"))
    assert wait_for(lambda: getattr(node.core.settings_for(f_t + 1), 'stamp_ns', None) == f_t, TIMEOUT)
    mark = client.diag_mark()
    q, _, _ = client.send(cloud_of(sim_scan(stamp())), outputs=False)
    assert q.error_code == ScanQuality.ERROR_FRAME_MISMATCH and "elsewhere" in q.message
    client.wait_diag_level(ERROR, mark)
    _set(node, check_frame=False)
    good()
    _set(node, check_frame=True)
    v_t = stamp()
    client.pub_settings.publish(settings_msg(base, v_t))
    assert wait_for(lambda v_t=v_t: getattr(node.core.settings_for(v_t + 1), 'stamp_ns', None) == v_t, TIMEOUT)
    good()
    assert node._worker.is_alive()

    # settings never received for this stamp (all settings are later): defaults, WARN on /diagnostics
    mark = client.diag_mark()
    q, dev, _ = client.send(cloud_of(sim_scan(1 * S)))
    assert q.settings_defaulted and q.error_code == ScanQuality.ERROR_NONE
    assert q.verdict >= ScanQuality.VERDICT_WARN and "defaults" in q.message
    assert q.settings.lateral_density == pytest.approx(10000.0)
    d = client.wait_diag_level(WARN, mark, lambda st: {kv.key: kv.value for kv in st.values}
                               .get("settings_defaulted") == "true")
    vals = {kv.key: kv.value for kv in d.status[0].values}
    assert vals["settings_defaulted"] == "true" and vals["model_id"] == node.core.model_id
    assert int(vals["scans_failed"]) >= 10


def test_services(rig):
    node, client, tester = rig
    explain = tester.create_client(Explain, "/xmetro_node/explain")
    recommend = tester.create_client(RecommendSettings, "/xmetro_node/recommend_settings")
    base = sim_scan(40 * S)
    client.pub_settings.publish(settings_msg(base, 39 * S))
    assert wait_for(lambda: getattr(node.core.settings_for(40 * S), 'stamp_ns', None) == 39 * S, TIMEOUT)
    msg = cloud_of(base)
    q, dev, _ = client.send(msg)
    assert q.error_code == ScanQuality.ERROR_NONE
    res = _offline(node, msg, base)
    valid_idx = np.asarray(res.prepared.index)[np.isfinite(res.predictions).all(axis=1)]

    # explain: explicit indices, all axes; additivity and equality with the published prediction (1e-9 m)
    req = Explain.Request()
    req.indices = [int(i) for i in valid_idx[::max(1, len(valid_idx) // 40)][:40]]
    r = call_service(explain, req, timeout=TIMEOUT)
    assert r.success, r.message
    P, F, A = len(req.indices), len(r.feature_names), 3
    model = node.core.model
    # the model's features, plus the set-context player for a PointNet model (its set neighbours' share)
    assert r.feature_names == list(model.feature_names) + (["set_context"] if model.has_sets else [])
    assert r.axis_names == ["x", "y", "z"] and len(r.feature_units) == F
    assert list(r.point_indices) == list(req.indices)
    shap = np.array(r.shap_values).reshape(P, F, A)
    pred = np.array(r.predictions).reshape(P, A)
    np.testing.assert_allclose(np.array(r.base_values) + shap.sum(axis=1), pred, rtol=0, atol=1e-9)
    # = exactly what ~/deviations published for these points (d = measured − nominal = −target), whatever the
    # model family: the SHAP values are contributions to the published d
    np.testing.assert_allclose(pred, -res.deviations[np.array(req.indices)] * 1e-3, rtol=0, atol=1e-9)
    d = _arrays(dev)
    published = np.column_stack([d["dx"], d["dy"], d["dz"]]).astype(np.float64)[np.array(req.indices)]
    np.testing.assert_allclose(pred, published, rtol=0, atol=1e-9)
    assert len(r.mean_abs_shap) == F * A and len(r.feature_values) == P * F
    np.testing.assert_allclose(np.array(r.mean_abs_shap).reshape(F, A), np.abs(shap).mean(axis=0), atol=1e-15)

    # one axis, sphere region of the latest scan by stamp, capped by max_points
    req = Explain.Request()
    req.scan_stamp = ns_to_stamp(40 * S)
    req.region_center.z = 0.0175
    req.region_radius = 0.004
    req.axes = Explain.Request.AXIS_Z
    req.max_points = 30
    r = call_service(explain, req, timeout=TIMEOUT)
    assert r.success, r.message
    assert r.axis_names == ["z"] and len(r.point_indices) == 30 and len(r.base_values) == 1
    pts = res.scan.points.reshape(-1, 3)[np.array(r.point_indices)]
    assert np.all(np.linalg.norm(pts - [0, 0, 17.5], axis=1) <= 4.0 + 1e-6)

    # explain failures: invalid index, unprocessed (NaN) index, empty region, too many indices, unknown scan
    nan_idx = int(np.flatnonzero(~np.isfinite(base.points.reshape(-1, 3)).all(axis=1))[0])
    for setup, text in (
        (lambda r: setattr(r, "indices", [msg.width * msg.height + 5]), "out of range"),
        (lambda r: setattr(r, "indices", [nan_idx]), "without a prediction"),
        (lambda r: (setattr(r.region_center, "x", 1.0), setattr(r, "region_radius", 0.001)), "no processed point"),
        (lambda r: setattr(r, "indices", [int(i) for i in valid_idx[:501]]), "cap"),
        (lambda r: setattr(r, "scan_stamp", ns_to_stamp(3 * S)), "no judged scan"),
        (lambda r: setattr(r, "axes", 8), "axes"),
    ):
        req = Explain.Request()
        setup(req)
        r = call_service(explain, req, timeout=TIMEOUT)
        assert not r.success and text in r.message, r.message

    # recommend: the cap region; 27 settings x 27 orientations by default (region subsampled to 300 points here to
    # keep the test quick with any model; the time budget bounds the answer time)
    assert all(x.successful for x in _set(node, recommend_max_points=300, recommend_max_seconds=20.0))
    req = RecommendSettings.Request()
    req.region_center.z = 0.0175
    req.region_radius = 0.006
    r = call_service(recommend, req, timeout=120.0)
    assert r.success, r.message
    assert "27 orientations" in r.message and "27 settings" in r.message
    scores = [a.score for a in r.alternatives]
    # ranked by the score (p95 of |d| + |U|); the answer is the best-ranked, whose p95 after is its predicted total
    # p95, unless its predicted gain is within its uncertainty (then the current set-up, and it says so)
    assert scores == sorted(scores)
    assert (r.alternatives[0].p95_abs_error == pytest.approx(r.p95_abs_error_after)
            or "keep the current set-up" in r.message)
    qn = np.array([r.recommended_orientation.x, r.recommended_orientation.y, r.recommended_orientation.z,
                   r.recommended_orientation.w])
    assert np.linalg.norm(qn) == pytest.approx(1.0)
    assert r.coverage_after >= min(0.95, r.coverage_before) - 1e-9
    assert r.meets_tolerance == (r.p95_abs_error_after <= node.get_parameter("tolerance").value)
    # given candidates, no tilt / turn search: the current orientation, the given settings
    req2 = RecommendSettings.Request()
    req2.indices = req.indices
    req2.region_center, req2.region_radius = req.region_center, req.region_radius
    req2.candidates = [settings_msg(base, 0)]
    req2.max_tilt = -1.0
    req2.max_turn = -1.0
    r2 = call_service(recommend, req2, timeout=120.0)
    assert r2.success and len(r2.alternatives) == 1, r2.message
    assert r2.recommended_orientation.w == pytest.approx(1.0)
    assert r2.p95_abs_error_after == pytest.approx(r2.p95_abs_error_before, rel=1e-6)
    # failures: empty region, bad candidate
    req3 = RecommendSettings.Request()
    req3.region_center.x = 1.0
    req3.region_radius = 0.001
    r3 = call_service(recommend, req3, timeout=TIMEOUT)
    assert not r3.success and "no processed point" in r3.message
    req4 = RecommendSettings.Request()
    req4.candidates = [settings_msg(base, 0, exposure_time=-1.0)]
    r4 = call_service(recommend, req4, timeout=TIMEOUT)
    assert not r4.success and "candidate 0" in r4.message
    assert stamp_ns_of(msg) == 40 * S


def test_corrected_is_built_only_while_someone_takes_it(rig, monkeypatch):
    """``~/corrected`` (~10 MB a 167k-point scan) is built and published only while it has a subscriber, as drivers
    do with the clouds nobody takes; ``~/deviations`` and ``~/quality`` are published regardless, and a subscriber
    that comes back gets the next scan's corrected cloud."""
    from xmetro_ros.ros import core as core_mod

    node, client, tester = rig
    client.pub_settings.publish(settings_msg(sim_scan(60 * S), 59 * S))
    built: list[int] = []
    real = core_mod.corrected_cloud

    def counting(*a, **kw):
        built.append(1)
        return real(*a, **kw)

    monkeypatch.setattr(core_mod, "corrected_cloud", counting)
    i = next(k for k, s in enumerate(client.subs) if s.topic_name.endswith("/corrected"))
    tester.destroy_subscription(client.subs[i])
    try:
        assert wait_for(lambda: node.pub_corr.get_subscription_count() == 0, TIMEOUT)
        q, _, _ = client.send(cloud_of(sim_scan(61 * S)), outputs=False)
        assert q.error_code == ScanQuality.ERROR_NONE, q.message
        assert wait_for(lambda: client._find("deviations", 61 * S) is not None, TIMEOUT)
        assert built == [] and client._find("corrected", 61 * S) is None
    finally:
        qos = client.subs[0].qos_profile
        client.subs[i] = tester.create_subscription(PointCloud2, f"/{client.target}/corrected",
                                                    client._add("corrected"), qos)
    client.wait_matched(node)
    _, dev, corr = client.send(cloud_of(sim_scan(62 * S)))
    assert built == [1] and corr is not None and corr.width * corr.height == dev.width * dev.height
