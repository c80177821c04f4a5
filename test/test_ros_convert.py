"""xmetro_ros.ros.convert: Scan ⇄ PointCloud2 (mm ⇄ m, organized kept, fields kept), settings ⇄ ScannerSettings."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from builtin_interfaces.msg import Time

from xmetro_ros.ros import cloud as C
from xmetro_ros.ros.convert import (
    LENGTH_FIELDS,
    cloud_to_scan,
    ns_to_stamp,
    scan_to_cloud,
    settings_from_msg,
    settings_to_msg,
    stamp_to_ns,
)
from xmetro_ros.scan.geometry import HeadPose
from xmetro_ros.scan.scan import Scan
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings, SettingsError

SETTINGS = ScanSettings(10.0, 4.0, 0.5)


def organized_scan() -> Scan:
    rng = np.random.default_rng(3)
    pts = rng.uniform(-40, 40, size=(4, 5, 3))
    pts[1, 2] = np.nan
    fields = {
        "intensity": rng.uniform(0, 1, (4, 5)).astype(np.float32),
        "line": np.repeat(np.arange(4, dtype=np.float32)[:, None], 5, axis=1),
        "u": rng.uniform(-30, 30, (4, 5)).astype(np.float32),
        "ring": np.arange(20, dtype=np.uint16).reshape(4, 5),
    }
    pose = HeadPose.looking_down(90.0, y_mm=-35.0).rotated(np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]]))
    return Scan(pts, SETTINGS, pose, "xm-ls90", fields, frame_id="artifact", stamp_ns=1_700_000_000_123_456_789)


def test_scan_to_cloud_metres_and_layout():
    scan = organized_scan()
    msg = scan_to_cloud(scan)
    assert (msg.height, msg.width) == (4, 5)
    assert [f.name for f in msg.fields] == ["x", "y", "z", "intensity", "line", "u", "ring"]
    assert msg.header.frame_id == "artifact" and stamp_to_ns(msg.header.stamp) == scan.stamp_ns
    assert not msg.is_dense
    # point (0, 1) by hand: x, y, z, intensity, line, u as float32 in metres / units, ring uint16
    p = scan.points[0, 1]
    f = scan.fields
    expected = struct.pack("<6fH", *(p / 1000.0), f["intensity"][0, 1], f["line"][0, 1], f["u"][0, 1] / 1000.0,
                           f["ring"][0, 1])
    step = msg.point_step
    assert step == 26
    assert bytes(msg.data)[step:2 * step] == expected
    assert "u" in LENGTH_FIELDS and "intensity" not in LENGTH_FIELDS
    msg2 = scan_to_cloud(scan, Time(sec=5, nanosec=7), fields=["u"])
    assert [f.name for f in msg2.fields] == ["x", "y", "z", "u"] and msg2.header.stamp.sec == 5
    with pytest.raises(KeyError):
        scan_to_cloud(scan, fields=["nope"])


def test_cloud_scan_round_trip_organized_and_unorganized():
    scan = organized_scan()
    back = cloud_to_scan(scan_to_cloud(scan), scan.settings, scan.pose, scan.scanner_id)
    assert back.organized and back.points.shape == (4, 5, 3) and back.points.dtype == np.float64
    np.testing.assert_allclose(back.points, scan.points, rtol=1e-6, atol=1e-5, equal_nan=True)
    assert np.isnan(back.points[1, 2]).all()
    assert set(back.fields) == {"intensity", "line", "u", "ring"}
    np.testing.assert_allclose(back.fields["u"], scan.fields["u"], rtol=1e-6)  # m → mm restored
    np.testing.assert_array_equal(back.fields["intensity"], scan.fields["intensity"])
    np.testing.assert_array_equal(back.fields["ring"], scan.fields["ring"])
    assert back.stamp_ns == scan.stamp_ns and back.frame_id == scan.frame_id
    flat = Scan(scan.points.reshape(-1, 3), SETTINGS, scan.pose, "xm-ls90",
                {"u": scan.fields["u"].reshape(-1)})
    fmsg = scan_to_cloud(flat)
    assert (fmsg.height, fmsg.width) == (1, 20)
    fback = cloud_to_scan(fmsg, SETTINGS, scan.pose, "xm-ls90", extra_fields=[])
    assert fback.points.shape == (20, 3) and fback.fields == {}
    with pytest.raises(C.CloudFormatError) as e:
        cloud_to_scan(fmsg, SETTINGS, scan.pose, "xm-ls90", extra_fields=["intensity"])
    assert e.value.code == "MISSING_INPUT_FIELD"


def test_settings_round_trip_si():
    scan = organized_scan()
    msg = settings_to_msg(SETTINGS, scan.pose, "artifact", 42, "xm-ls90")
    assert msg.lateral_density == pytest.approx(10_000.0)
    assert msg.direction_density == pytest.approx(4_000.0)
    assert msg.exposure_time == pytest.approx(5e-4)
    assert msg.head_pose.position.y == pytest.approx(-0.035) and msg.head_pose.position.z == pytest.approx(0.09)
    s, pose, sid, frame, stamp = settings_from_msg(msg, ScannerModel.load().settings_range)
    assert s.as_tuple() == pytest.approx(SETTINGS.as_tuple())
    np.testing.assert_allclose(pose.position, scan.pose.position, atol=1e-9)
    np.testing.assert_allclose(pose.rotation, scan.pose.rotation, atol=1e-9)
    assert (sid, frame, stamp) == ("xm-ls90", "artifact", 42)


@pytest.mark.parametrize(
    "attr,value", [("lateral_density", 0.0), ("direction_density", -1.0), ("exposure_time", math.nan),
                   ("exposure_time", math.inf)])
def test_settings_from_msg_rejects_bad_values(attr, value):
    msg = settings_to_msg(SETTINGS, HeadPose.looking_down())
    setattr(msg, attr, value)
    with pytest.raises(SettingsError, match=attr):
        settings_from_msg(msg)


def test_settings_from_msg_ranges_and_pose():
    msg = settings_to_msg(ScanSettings(500.0, 4.0, 0.5), HeadPose.looking_down())
    settings_from_msg(msg)  # no ranges: accepted
    with pytest.raises(SettingsError, match="outside"):
        settings_from_msg(msg, ScannerModel.load().settings_range)
    msg = settings_to_msg(SETTINGS, HeadPose.looking_down())
    msg.head_pose.orientation.w = 0.0
    with pytest.raises(SettingsError, match="orientation"):
        settings_from_msg(msg)
    msg = settings_to_msg(SETTINGS, HeadPose.looking_down())
    msg.head_pose.position.x = math.nan
    with pytest.raises(SettingsError, match="position"):
        settings_from_msg(msg)
    msg = settings_to_msg(SETTINGS, HeadPose.looking_down())
    msg.head_pose.orientation.w = 2.0  # not normalised: accepted and normalised
    assert np.allclose(settings_from_msg(msg)[1].rotation, np.eye(3))


def test_stamps():
    assert stamp_to_ns(ns_to_stamp(1_234_567_890_123)) == 1_234_567_890_123
    t = ns_to_stamp(2_500_000_001)
    assert (t.sec, t.nanosec) == (2, 500_000_001)
    with pytest.raises(ValueError):
        ns_to_stamp(-1)
