"""A scanner described in data-sheet terms (measuring range, field of view, triangulation angle, camera side),
and a camera that is not at the laser's height on +Y: geometry, features and the simulator follow it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from xmetro_ros.scan.artifacts import Sphere
from xmetro_ros.scan.geometry import HeadPose, point_geometry
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings
from xmetro_ros.sim import simulate_scan

RANGES = {"lateral_density": [0.5, 100], "direction_density": [0.1, 50], "exposure_ms": [0.005, 50]}
DEFAULTS = {"lateral_density": 5.0, "direction_density": 3.0, "exposure_ms": 0.5}


def datasheet(**over: object) -> dict:
    d = {"id": "ls-200", "serial": "SN-0042", "measuring_range_mm": [150.0, 250.0],
         "field_of_view_mm": [100.0, 180.0], "triangulation_angle_deg": 20.0, "camera_side": "-y",
         "settings_range": RANGES, "default_settings": DEFAULTS}
    d.update(over)
    return d


def test_the_packaged_description_is_unchanged():
    m = ScannerModel.load()
    assert m.camera_mm == (0.0, 52.0, 0.0) and m.baseline_mm == 52.0 and m.standoff_mm == 90.0
    assert m.triangulation_angle_deg == pytest.approx(math.degrees(math.atan2(52, 90)))
    assert len(m.study_configurations()) == 27


def test_datasheet_terms_give_the_geometry():
    m = ScannerModel.from_dict(datasheet(), "sheet")
    # fan edges: half-width grows by 40 mm over 100 mm → they meet 125 mm before the near end (50 / 0.4)
    assert m.depth_of_field_mm == pytest.approx((125.0, 225.0))
    assert m.standoff_mm == pytest.approx(175.0)
    assert m.fan_angle_deg == pytest.approx(math.degrees(2 * math.atan(0.4)))
    assert m.sensor_origin_mm == pytest.approx((0.0, 0.0, 25.0))  # the range is counted from 25 mm behind the source
    assert m.camera_mm[1] == pytest.approx(-175.0 * math.tan(math.radians(20.0)))
    assert m.triangulation_angle_deg == pytest.approx(20.0)
    assert m.serial == "SN-0042" and m.settings_levels is None
    with pytest.raises(ValueError, match="no settings levels"):
        m.study_configurations()
    lv = {"lateral_density": (2, 4, 6), "direction_density": (1, 2, 3), "exposure_ms": (0.2, 0.5, 1.0)}
    assert len(m.with_levels(lv).study_configurations()) == 27


@pytest.mark.parametrize("bad, match", [
    ({"field_of_view_mm": [180.0, 100.0]}, "grow with distance"),
    ({"measuring_range_mm": [250.0, 150.0]}, "increasing"),
    ({"triangulation_angle_deg": 95.0}, r"\(0, 90\)"),
    ({"camera_side": "left"}, "camera_side"),
])
def test_bad_datasheet_values_are_named(bad, match):
    with pytest.raises(ValueError, match=match):
        ScannerModel.from_dict(datasheet(**bad), "sheet")


def test_camera_direction_follows_any_camera_position():
    pts = np.array([[0.0, 0.0, 0.0], [20.0, 5.0, -3.0], [-15.0, -8.0, 4.0]])
    pose = HeadPose.looking_down(175.0)
    for cam in [(0.0, 52.0, 0.0), (0.0, -63.7, 0.0), (0.0, -60.0, -30.0), (10.0, 40.0, 5.0)]:
        g = point_geometry(pts, pose, cam)
        # independent: the camera moves with the source of each point's profile (same head y as the point)
        src = np.c_[np.zeros(3), pts[:, 1], np.full(3, 175.0)]
        cam_w = src + np.asarray(cam)  # looking down: head axes = world axes
        want = (cam_w - pts) / np.linalg.norm(cam_w - pts, axis=1, keepdims=True)
        np.testing.assert_allclose(g.V, want, atol=1e-12)
    # a number is a baseline along +Y, as before
    np.testing.assert_allclose(point_geometry(pts, pose, 52.0).V, point_geometry(pts, pose, (0, 52.0, 0)).V)


def test_simulator_sees_from_the_described_camera():
    """A camera on -Y: the simulated points are seen from -Y (V_y < 0) and the scan still covers the sphere."""
    m = ScannerModel.from_dict(datasheet(effects=ScannerModel.load().effects), "sheet")
    scan = simulate_scan(Sphere(25.0), ScanSettings(5.0, 3.0, 0.5), scanner=m, seed=3)
    ok = np.isfinite(scan.points).all(axis=-1)
    assert ok.sum() > 1000
    p = scan.points[ok]
    g = point_geometry(p, scan.pose, m.camera_mm)
    assert (g.V[:, 1] < 0).all()
    # every returned point faces the camera (the simulator's visibility used the same camera)
    n = Sphere(25.0).normals(Sphere(25.0).project(p))
    assert (np.einsum("ij,ij->i", n, g.V) > 0).mean() > 0.99
