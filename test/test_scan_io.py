"""scan_io: scans ⇄ MCAP (PointCloud2 + ScannerSettings + per-scan records + manifest)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import need_shared

from xmetro_ros.bag.reader import BagReader
from xmetro_ros.ros.convert import settings_from_msg, stamp_to_ns
from xmetro_ros.ros.scan_io import ScanBagError, read_manifest, read_scans, write_scans
from xmetro_ros.scan.artifacts import Cylinder, Sphere
from xmetro_ros.scan.geometry import HeadPose
from xmetro_ros.scan.scan import Scan
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings

ROOT = Path(__file__).resolve().parents[1]
BAGS = ROOT.parent / "shared" / "data" / "bags"


def _scans() -> list[Scan]:
    rng = np.random.default_rng(3)
    out = []
    for i, art in enumerate([Sphere(22.5, (0.0, 0.0, 0.0)), Cylinder(20.0)]):
        h, w = 12, 30
        pts = rng.normal(size=(h, w, 3)) * 15 + [0, 0, 10]
        pts[0, :5] = np.nan
        err = rng.normal(size=(h, w, 3)) * 0.02
        err[0, :5] = np.nan
        fields = {"intensity": rng.random((h, w)).astype(np.float32),
                  "u": (rng.random((h, w)) * 30).astype(np.float32),
                  "line": np.repeat(np.arange(h, dtype=np.float32)[:, None], w, axis=1)}
        out.append(Scan(pts, ScanSettings(1.0 + i, 2.0, 0.5), HeadPose.looking_down(90.0, y_mm=-30.0 + i), "xm-ls90",
                        fields, artifact=art, expected_error=err, meta={"seed": i, "effects": {"noise": {"s": 1}}}))
    # an unorganized scan without artifact or expected error, with its own stamp
    out.append(Scan(rng.normal(size=(40, 3)), ScanSettings(1.5, 1.0, 1.0), HeadPose.looking_down(), "xm-ls90",
                    stamp_ns=123))
    return out


def _check(a: Scan, b: Scan, atol: float) -> None:
    assert b.shape == a.shape and b.organized == a.organized
    np.testing.assert_allclose(b.points, a.points, atol=atol, rtol=0, equal_nan=True)
    assert b.settings == a.settings and b.scanner_id == a.scanner_id and b.frame_id == a.frame_id
    np.testing.assert_allclose(b.pose.position, a.pose.position, atol=1e-12)
    assert b.stamp_ns == a.stamp_ns and b.meta == a.meta
    assert (b.artifact.to_dict() if b.artifact else None) == (a.artifact.to_dict() if a.artifact else None)
    assert set(b.fields) == set(a.fields)
    for k in a.fields:
        assert b.fields[k].dtype == a.fields[k].dtype
        np.testing.assert_allclose(b.fields[k], a.fields[k], atol=atol, rtol=1e-7)
    if a.expected_error is None:
        assert b.expected_error is None
    else:
        np.testing.assert_allclose(b.expected_error, a.expected_error, atol=atol * 1e-2, rtol=1e-6, equal_nan=True)


def test_roundtrip_float32_wire_and_exact(tmp_path):
    scans = _scans()
    manifest = {"campaign": "test", "items": [{"artifact": "sphere"}, {"artifact": "cylinder"}]}
    write_scans(tmp_path / "a.mcap", scans, manifest)
    write_scans(tmp_path / "b.mcap", scans, manifest, exact=True, compression=None)
    assert read_manifest(tmp_path / "a.mcap") == manifest
    for a, b in zip(scans, read_scans(tmp_path / "a.mcap"), strict=True):
        _check(a, b, atol=1e-4)  # float32 metres on the wire
    for a, b in zip(scans, read_scans(tmp_path / "b.mcap"), strict=True):
        _check(a, b, atol=0.0)  # bit for bit
        assert b.points.dtype == np.float64


def test_bag_layout_is_usable_by_ros_tools(tmp_path):
    scans = _scans()
    write_scans(tmp_path / "c.mcap", scans)
    r = BagReader(tmp_path / "c.mcap")
    assert r.topics() == {"/scan": "sensor_msgs/msg/PointCloud2", "/scanner_settings": "xmetro_ros/msg/ScannerSettings"}
    msgs = r.read_all()
    assert [m.topic for m in msgs] == ["/scanner_settings", "/scan"] * len(scans)
    for (s, c), scan in zip(zip(msgs[::2], msgs[1::2], strict=True), scans, strict=True):
        st, _pose, sid, frame, t = settings_from_msg(s.msg)
        assert t < stamp_to_ns(c.msg.header.stamp) and frame == c.msg.header.frame_id and sid == "xm-ls90"
        np.testing.assert_allclose(st.as_tuple(), scan.settings.as_tuple())
        names = [f.name for f in c.msg.fields]
        assert names[:3] == ["x", "y", "z"]
        if scan.expected_error is not None:
            assert {"ex", "ey", "ez"} <= set(names) and c.msg.height == scan.shape[0]
    assert read_manifest(tmp_path / "c.mcap") is None


def test_simulated_scan_roundtrip(tmp_path):
    from xmetro_ros.sim import simulate_scan

    model = ScannerModel.load()
    scan = simulate_scan(Sphere(22.5, (0.0, 0.0, 0.0)), model.study_configurations()[4], seed=7)
    write_scans(tmp_path / "sim.mcap", [scan], {"seed": 7})
    (back,) = read_scans(tmp_path / "sim.mcap")
    _check(scan, back, atol=1e-4)
    assert back.meta["seed"] == 7 and back.n_valid == scan.n_valid


def test_foreign_clouds_get_default_settings_and_errors_are_clear(tmp_path):
    need_shared(BAGS)
    scans = read_scans(BAGS / "rosbag2_pointcloud2_truck", topic="cloud_2")
    (s,) = scans
    model = ScannerModel.load()
    assert s.meta["settings_defaulted"] and s.settings == model.default_settings
    assert s.points.shape == (35200, 3) and s.frame_id == "test" and s.stamp_ns == 0
    with pytest.raises(ScanBagError, match="no topic /scan"):
        read_scans(BAGS / "rosbag2_talker")
    with pytest.raises(ValueError, match="reserved"):
        bad = _scans()[0]
        bad.fields["ex"] = np.zeros(bad.shape, np.float32)
        write_scans(tmp_path / "bad.mcap", [bad])
