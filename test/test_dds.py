"""DDS acceptance between two processes over localhost-only DDS (our Fast DDS profile, private domain).

The peer (test/dds_peer.py) runs in a separate process; this process runs a node in a background thread. Covered:
ScannerSettings and ScanQuality both ways, both services (Explain, RecommendSettings), a 180,000-point 7-field
PointCloud2 round trip (byte-identical), and transient-local late joining of latched settings.
Every exchange waits for DDS matching first and republishes until the reply arrives (30 s timeouts).
"""

from __future__ import annotations

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point
from ros_harness import ROOT, Inbox, PeerProcess, publish_until, qos, spin_node
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header

from xmetro_ros.msg import ScannerSettings, ScanQuality
from xmetro_ros.ros.cloud import create_cloud_from_arrays, xyz_fields
from xmetro_ros.ros.convert import ns_to_stamp, settings_from_msg, settings_to_msg, stamp_to_ns
from xmetro_ros.ros.rclpy_util import call_service
from xmetro_ros.scan.geometry import HeadPose
from xmetro_ros.scan.scanner import ScanSettings
from xmetro_ros.srv import Explain, RecommendSettings

NS = "/xm_peer"
pytestmark = pytest.mark.timeout(120)


@pytest.fixture(scope="module")
def peer():
    with PeerProcess(ROOT / "test" / "dds_peer.py", "--ns", NS, "--lifetime", "150") as p:
        yield p
    assert p.proc.returncode == 0, p.text()


@pytest.fixture(scope="module")
def node(peer):
    with spin_node("dds_test") as spinner:
        yield spinner.node


def big_cloud(n: int = 180_000) -> PointCloud2:
    """A 180k-point cloud with the simulator's 7 float32 fields (x, y, z, intensity, line, t, u), some NaN."""
    rng = np.random.default_rng(7)
    arrays = {k: rng.normal(size=n).astype(np.float32) for k in ("x", "y", "z", "intensity", "line", "t", "u")}
    arrays["x"][::97] = np.nan
    header = Header(frame_id="artifact", stamp=Time(sec=1_700_000_000, nanosec=5))
    return create_cloud_from_arrays(header, arrays, height=600, width=300)


def test_scanner_settings_and_quality_both_ways(node):
    sent = settings_to_msg(ScanSettings(6.0, 5.0, 0.1), HeadPose.looking_down(90.0, y_mm=-12.5), "artifact",
                           1_700_000_001_000_000_000, "xm-ls90")
    inbox = Inbox(node, ScannerSettings, f"{NS}/settings_out", qos(1, latched=True))
    pub = node.create_publisher(ScannerSettings, f"{NS}/settings_in", qos(2))
    got = publish_until(pub, sent, inbox, lambda m: stamp_to_ns(m.header.stamp) == 1_700_000_001_000_000_000)
    settings, pose, sid, frame, _stamp = settings_from_msg(got)
    assert settings.as_tuple() == pytest.approx((6.0, 5.0, 0.1))
    np.testing.assert_allclose(pose.position, [0.0, -12.5, 90.0], atol=1e-9)
    assert (sid, frame) == ("xm-ls90", "artifact")

    q = ScanQuality(model_id="m1", verdict=ScanQuality.VERDICT_RESCAN, error_code=ScanQuality.ERROR_NONE,
                    message="too few usable points", points_received=10, points_valid=9, points_flagged=4)
    q.header.stamp = ns_to_stamp(77)
    q.flag_names = ["OUTLIER"]
    q.flag_counts = [4]
    q.mean_abs_error = [1e-5, 2e-5, 3e-5]
    q.settings = sent
    q.settings_defaulted = True
    qin = Inbox(node, ScanQuality, f"{NS}/quality_out", qos(1, latched=True))
    qpub = node.create_publisher(ScanQuality, f"{NS}/quality_in", qos(2))
    back = publish_until(qpub, q, qin, lambda m: m.header.stamp.nanosec == 77)
    assert back.verdict == ScanQuality.VERDICT_RESCAN and back.message == "too few usable points"
    assert list(back.flag_counts) == [4] and list(back.mean_abs_error) == [1e-5, 2e-5, 3e-5]
    assert back.settings.lateral_density == sent.lateral_density and back.settings_defaulted


def test_late_joiner_gets_latched_settings_and_quality(node, peer):
    # The peer published both at start-up, before these subscriptions existed: transient local delivers them.
    from dds_peer import latched_quality, latched_settings

    s = Inbox(node, ScannerSettings, f"{NS}/settings_latched", qos(1, latched=True)).wait()
    assert s == latched_settings()
    settings, *_ = settings_from_msg(s)
    assert settings.as_tuple() == pytest.approx((15.0, 3.0, 2.0))
    q = Inbox(node, ScanQuality, f"{NS}/quality_latched", qos(1, latched=True)).wait()
    assert q == latched_quality()


def test_explain_service(node):
    client = node.create_client(Explain, f"{NS}/explain")
    req = Explain.Request(indices=[3, 10, 42], axes=Explain.Request.AXIS_X | Explain.Request.AXIS_Z)
    res = call_service(client, req, timeout=30.0)
    assert res.success and res.model_id == "peer-model"
    assert list(res.axis_names) == ["x", "z"] and list(res.point_indices) == [3, 10, 42]
    f = len(res.feature_names)
    shap = np.asarray(res.shap_values).reshape(3, f, 2)
    pred = np.asarray(res.predictions).reshape(3, 2)
    np.testing.assert_allclose(np.asarray(res.base_values) + shap.sum(axis=1), pred, rtol=0, atol=1e-15)
    assert shap[2, 1, 1] == pytest.approx(1e-6 * 43 * 2 * 3)
    region = call_service(client, Explain.Request(region_center=Point(x=0.0, y=0.0, z=0.04), region_radius=0.01,
                                                  max_points=4), timeout=30.0)
    assert list(region.point_indices) == [0, 1, 2, 3] and list(region.axis_names) == ["x", "y", "z"]


def test_recommend_settings_service(node):
    client = node.create_client(RecommendSettings, f"{NS}/recommend_settings")
    pose = HeadPose.looking_down()
    cands = [settings_to_msg(ScanSettings(lat, 4.0, 0.5), pose) for lat in (6.0, 15.0, 10.0)]
    res = call_service(client, RecommendSettings.Request(candidates=cands, tolerance=2e-6), timeout=30.0)
    assert res.success
    assert res.recommended_settings.lateral_density == pytest.approx(15_000.0)
    assert [a.settings.lateral_density for a in res.alternatives] == pytest.approx([15_000.0, 10_000.0, 6_000.0])
    assert res.meets_tolerance  # 2 * 1e-5 / 15 = 1.33e-6 <= 2e-6
    assert res.recommended_orientation.w == 1.0


def test_large_cloud_round_trip_is_byte_identical(node):
    cloud = big_cloud()
    assert len(cloud.data) == 180_000 * 28
    inbox = Inbox(node, PointCloud2, f"{NS}/cloud_out", qos(1, latched=True))
    pub = node.create_publisher(PointCloud2, f"{NS}/cloud_in", qos(1))
    back = publish_until(pub, cloud, inbox, lambda m: m.header.stamp.nanosec == 5, timeout=60.0, period=10.0)
    assert (back.height, back.width, back.point_step, back.row_step) == (600, 300, 28, 8400)
    assert [(f.name, f.offset, f.datatype, f.count) for f in back.fields] == [
        (f.name, f.offset, f.datatype, f.count) for f in cloud.fields]
    assert back.is_bigendian == cloud.is_bigendian and back.is_dense == cloud.is_dense
    assert back.header == cloud.header
    assert bytes(back.data) == bytes(cloud.data)
    xyz, extra = xyz_fields(back, ["u"])
    assert xyz.shape == (180_000, 3) and np.isnan(xyz[::97, 0]).all() and extra["u"].dtype == np.float32
