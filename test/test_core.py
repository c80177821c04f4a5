"""Core vocabulary: head poses and per-point geometry, scanner model and settings, artifacts, Scan."""

from __future__ import annotations

import numpy as np
import pytest

from xmetro_ros.scan.artifact_specs import artifact_from_dict, parse_artifact
from xmetro_ros.scan.artifacts import ArtifactSpecError, Cylinder, Plane, Sphere
from xmetro_ros.scan.geometry import HeadPose, matrix_to_quat, point_geometry, quat_to_matrix
from xmetro_ros.scan.scan import Scan
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings, SettingsError


def test_quaternion_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        r = quat_to_matrix(q)
        assert np.allclose(r.T @ r, np.eye(3), atol=1e-12)
        q2 = matrix_to_quat(r)
        assert np.allclose(q2 if np.dot(q, q2) > 0 else -q2, q, atol=1e-9)
    with pytest.raises(ValueError, match="zero"):
        quat_to_matrix([0, 0, 0, 0])


def test_geometry_of_the_study_setup():
    pose = HeadPose.looking_down(90.0)
    pts = np.array([[0.0, 0.0, 20.0], [10.0, 5.0, 0.0]])
    g = point_geometry(pts, pose, camera_mm=52.0)
    # The point under the source: laser straight up, stand-off = 90 - Z (the study's R_y).
    assert np.allclose(g.L[0], [0, 0, 1])
    assert np.allclose(g.standoff, 90.0 - pts[:, 2])
    # The source lies at the point's scan coordinate: no Y component in L; the camera sits at +52 mm along Y.
    assert np.allclose(g.L[:, 1], 0.0)
    assert np.allclose(g.V[0], np.array([0, 52.0, 70.0]) / np.hypot(52.0, 70.0))
    assert np.allclose(g.u, pts[:, 0]) and np.allclose(g.s, pts[:, 1])
    assert np.allclose(g.source_distance[1], np.hypot(10.0, 90.0))


def test_rotated_pose_about_pivot_keeps_distance():
    pose = HeadPose.looking_down(90.0)
    turned = pose.rotated(quat_to_matrix([0, np.sin(0.2), 0, np.cos(0.2)]), pivot=np.zeros(3))
    assert np.isclose(np.linalg.norm(turned.position), 90.0)
    # The laser axis (-Z head) still points at the pivot.
    assert np.allclose(turned.to_head(np.zeros((1, 3)))[0, :2], 0.0, atol=1e-9)
    with pytest.raises(ValueError, match="rotation"):
        HeadPose(np.zeros(3), np.diag([1.0, 1.0, -1.0]))


def test_scanner_model_and_settings():
    sc = ScannerModel.load()
    assert sc.id == "xm-ls90" and np.isclose(sc.triangulation_angle_deg, np.degrees(np.arctan2(52, 90)))
    confs = sc.study_configurations()
    assert len(confs) == 27 and len(set(confs)) == 27
    s = ScanSettings(10.0, 4.0, 0.5)
    si = s.to_si()
    assert si == {"lateral_density": 10000.0, "direction_density": 4000.0, "exposure_time": 0.0005}
    assert ScanSettings.from_si(**si) == s
    with pytest.raises(SettingsError, match="exposure_ms"):
        ScanSettings(10.0, 4.0, -1.0).validate()
    with pytest.raises(SettingsError, match="outside"):
        sc.validate_settings(ScanSettings(1000.0, 4.0, 0.5))
    with pytest.raises(ValueError, match="missing or malformed"):
        ScannerModel.from_dict({"id": "x"})


def test_artifact_errors_are_the_study_equations():
    sph = Sphere(20.0)
    p = np.array([[0.0, 0.0, 21.0], [3.0, 4.0, 0.0]])
    e = sph.errors(p)
    assert np.allclose(e[0], [0, 0, -1.0])  # measured outside on +Z: negative error (eq. 15)
    assert np.allclose(p[1] + e[1], p[1] * 20.0 / 5.0)
    cyl = Cylinder(10.0)
    ec = cyl.errors(np.array([[0.0, 7.0, 11.0]]))
    assert np.allclose(ec, [[0.0, 0.0, -1.0]])  # axial projection: no Y error
    pl = Plane((0, 0, 1.0), (0, 0, 1.0))
    assert np.allclose(pl.errors(np.array([[5.0, 5.0, 1.5]])), [[0, 0, -0.5]])
    # Ray casting: from above, the first hit is the top of the sphere.
    t = sph.intersect(np.array([[0.0, 0.0, 90.0], [50.0, 0, 90.0]]), np.array([[0, 0, -1.0], [0, 0, -1.0]]))
    assert np.isclose(t[0], 70.0) and np.isnan(t[1])
    assert np.allclose(cyl.normals(np.array([[0.0, 3.0, 10.0]])), [[0, 0, 1.0]])
    for a in (sph, cyl, pl):
        assert artifact_from_dict(a.to_dict()) == a


def test_parse_artifact_and_errors():
    a, fit = parse_artifact("sphere:radius=40,center=fit")
    assert a == Sphere(40.0) and fit
    a, fit = parse_artifact("cylinder:radius=20,center=1;2;3")
    assert isinstance(a, Cylinder) and a.center == (1.0, 2.0, 3.0) and not fit
    for bad, msg in [("", "empty"), ("cube:radius=3", "unknown artifact"), ("sphere", "needs radius"),
                     ("sphere:radius=abc", "not a number"), ("sphere:radius=-1", "positive"),
                     ("sphere:radius=4,color=red", "unknown option"), ("sphere:radius=4,center=1;2", "three")]:
        with pytest.raises(ArtifactSpecError, match=msg):
            parse_artifact(bad)


def test_scan_container():
    pts = np.full((2, 3, 3), np.nan)
    pts[0, 1] = [1, 2, 3]
    scan = Scan(pts, ScanSettings(10, 4, 0.5), HeadPose.looking_down(), "xm-ls90",
                fields={"intensity": np.ones((2, 3))})
    assert scan.organized and scan.shape == (2, 3) and scan.n_valid == 1
    p, f, idx = scan.flat()
    assert idx.tolist() == [1] and p.shape == (1, 3) and f["intensity"].shape == (1,)
    with pytest.raises(ValueError, match="field 'intensity'"):
        Scan(pts, ScanSettings(10, 4, 0.5), HeadPose.looking_down(), "x", fields={"intensity": np.ones(6)})
