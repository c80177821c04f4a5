"""One sign for every deviation a user sees (issue 27, docs/conventions.md "Errors and deviations: one sign"):
d = measured − nominal on ``~/deviations`` (dx, dy, dz), in ``xmetro predict``'s bags, on ``~/explain`` and on
``~/cad_deviations`` (measured − CAD), with ``~/corrected`` = measured − d; inside the package the study's target
t = nominal − measured, turned once by ``scan.targets.published_deviation`` / ``study_target``.

Pinned end to end with the simulator as truth, the truth computed here from the geometry (not through the function
under test): a simulated sphere scan judged by the node's core (``XmetroCore``, what the live node and ``xmetro
predict`` run), and the shipped demo bag through ``xmetro predict``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_node_helpers import cloud_of, settings_msg

from xmetro_ros.ros.core import XmetroCore
from xmetro_ros.ros.node_outputs import cloud_arrays, deviation_arrays, read_outputs
from xmetro_ros.ros.params import PARAMS
from xmetro_ros.scan.artifacts import Sphere
from xmetro_ros.scan.scanner import ScanSettings
from xmetro_ros.scan.targets import published_deviation, study_target
from xmetro_ros.sim import simulate_scan
from xmetro_ros.srv import Explain

ROOT = Path(__file__).resolve().parents[1]
S = 1_000_000_000
RADIUS = 17.5


def _core(**values) -> XmetroCore:
    core = XmetroCore({p.name: p.default for p in PARAMS} | {"min_valid_points": 50, **values})
    assert core.model is not None, core.degraded
    return core


def _measured_minus_nominal(p_mm: np.ndarray, radius: float) -> np.ndarray:
    """measured − nominal per axis on a sphere at the origin: the point minus its radial projection."""
    r = np.linalg.norm(p_mm, axis=1, keepdims=True)
    return p_mm - radius * p_mm / r


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.corrcoef(a, b)[0, 1])


@pytest.fixture(scope="module")
def judged():
    scan = simulate_scan(Sphere(RADIUS, np.zeros(3)), ScanSettings(6.0, 3.0, 0.5), seed=2727, stamp_ns=10 * S)
    core = _core()
    core.add_settings(settings_msg(scan, 9 * S))
    out = core.judge(cloud_of(scan))
    assert out.deviations is not None and out.corrected is not None, out.quality.message
    return core, scan, out


def test_published_deviation_is_measured_minus_nominal(judged) -> None:
    _, scan, out = judged
    a = cloud_arrays(out.deviations)
    d = np.stack([a["dx"], a["dy"], a["dz"]], axis=1).astype(np.float64) * 1e3  # mm
    pts = scan.points.reshape(-1, 3)
    ok = np.isfinite(d).all(axis=1) & np.isfinite(pts).all(axis=1)
    ok &= ~scan.injected_outlier.reshape(-1) if scan.injected_outlier is not None else ok
    assert ok.sum() > 5000
    actual = _measured_minus_nominal(pts[ok], RADIUS)  # noise included
    systematic = -scan.expected_error.reshape(-1, 3)[ok]  # the simulator's noise-free error, nominal − measured
    for k in range(3):
        # the sign: positively correlated with the truth measured − nominal on every axis
        assert _corr(d[ok, k], actual[:, k]) > 0.5, ("actual", k, _corr(d[ok, k], actual[:, k]))
        assert _corr(d[ok, k], systematic[:, k]) > 0.8, ("systematic", k, _corr(d[ok, k], systematic[:, k]))
    # along the outward normal: positive = measured outside the sphere, as a CAD map reads
    n = pts[ok] / np.linalg.norm(pts[ok], axis=1, keepdims=True)
    assert _corr(np.einsum("ij,ij->i", d[ok], n), np.einsum("ij,ij->i", actual, n)) > 0.5
    # the compensation lowers the error: mean |radial error| of measured − d below that of the measured points
    after = pts[ok] - d[ok]
    assert np.abs(np.linalg.norm(after, axis=1) - RADIUS).mean() < 0.8 * np.abs(np.linalg.norm(pts[ok], axis=1)
                                                                                - RADIUS).mean()


def test_corrected_is_measured_minus_d(judged) -> None:
    _, _, out = judged
    dv, cv = cloud_arrays(out.deviations), cloud_arrays(out.corrected)
    fin = np.isfinite(dv["dx"]) & np.isfinite(dv["dy"]) & np.isfinite(dv["dz"])
    assert fin.sum() > 5000
    for k in "xyz":
        x, d, c = (np.asarray(v, np.float64) for v in (dv[k], dv["d" + k], cv[k]))
        # float32 on the wire: within two float32 ulps of the coordinate (~4 nm at 2 cm)
        np.testing.assert_allclose(c[fin], x[fin] - d[fin], rtol=0, atol=5e-9)
        np.testing.assert_array_equal(c[~fin], x[~fin])  # no prediction: the point as received


def test_explain_explains_the_published_d(judged) -> None:
    core, _scan, out = judged
    a = cloud_arrays(out.deviations)
    fin = np.flatnonzero(np.isfinite(a["dx"]))
    req = Explain.Request()
    req.indices = [int(i) for i in fin[:: max(1, len(fin) // 20)][:20]]
    r = core.explain(req)
    assert r.success, r.message
    P, F = len(req.indices), len(r.feature_names)
    pred = np.asarray(r.predictions).reshape(P, 3)
    d = np.stack([a["dx"], a["dy"], a["dz"]], axis=1).astype(np.float64)[np.asarray(req.indices)]
    np.testing.assert_allclose(pred, d, rtol=0, atol=1e-9)
    shap = np.asarray(r.shap_values).reshape(P, F, 3)
    np.testing.assert_allclose(np.asarray(r.base_values) + shap.sum(axis=1), pred, rtol=0, atol=1e-9)


def test_cad_map_has_the_sign_of_the_deviations(judged, tmp_path) -> None:
    """A sphere's CAD (a fine tessellation) at the identity pose: ``before`` = measured − CAD follows the
    published radial deviation's truth, and ``before − after`` (what the compensation moved the point along the
    normal) is d along the normal, so both outputs read the same way."""
    o3d = pytest.importorskip("open3d")
    from xmetro_ros.scan.mesh import write_stl

    _, scan, _ = judged
    m = o3d.geometry.TriangleMesh.create_sphere(radius=RADIUS, resolution=200)
    stl = write_stl(tmp_path / "sphere.stl", np.asarray(m.vertices), np.asarray(m.triangles))
    core = _core(cad_mesh=str(stl), cad_pose=[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
    core.add_settings(settings_msg(scan, 9 * S))
    out = core.judge(cloud_of(scan))
    assert out.cad is not None, out.cad_error
    c, a = cloud_arrays(out.cad), cloud_arrays(out.deviations)
    idx = np.asarray(c["index"], np.int64)
    pts = np.stack([c["x"], c["y"], c["z"]], axis=1).astype(np.float64) * 1e3
    n = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    truth = np.einsum("ij,ij->i", _measured_minus_nominal(pts, RADIUS), n)
    before, after = c["before"].astype(np.float64) * 1e3, c["after"].astype(np.float64) * 1e3
    assert _corr(before, truth) > 0.99
    d_n = np.einsum("ij,ij->i", np.stack([a["dx"], a["dy"], a["dz"]], axis=1)[idx].astype(np.float64) * 1e3, n)
    assert _corr(before - after, d_n) > 0.95
    np.testing.assert_allclose(np.median((before - after) / d_n), 1.0, atol=0.05)


def test_predict_bag_publishes_measured_minus_nominal(tmp_path) -> None:
    """``xmetro predict`` on the shipped demo bag (its goldens): dx, dy, dz against the simulator's noise-free error
    the bag carries (ex, ey, ez: nominal − measured, training data); ``deviation_arrays`` reads them back as the
    study's target."""
    from xmetro_ros.apps.predict import predict_bag
    from xmetro_ros.ros.scan_io import read_scans

    bag = ROOT / "bags" / "demo.mcap"
    predict_bag(bag, tmp_path / "pred.mcap")
    outs, scans = read_outputs(tmp_path / "pred.mcap"), read_scans(bag)
    assert len(outs) == len(scans) == 4
    for o, scan in zip(outs, scans, strict=True):
        a = cloud_arrays(o.deviations)
        d = np.stack([a["dx"], a["dy"], a["dz"]], axis=1).astype(np.float64) * 1e3
        _pts, t, _flags = deviation_arrays(o.deviations)
        np.testing.assert_array_equal(t, -d)  # the reader turns the sign back, exactly
        mmn = -np.asarray(scan.expected_error, np.float64).reshape(-1, 3)  # measured − nominal, noise-free
        ok = np.isfinite(d).all(axis=1) & np.isfinite(mmn).all(axis=1)
        for k in range(3):
            if np.std(mmn[ok, k]) > 1e-4:  # an axis with no error (the cylinder's axis) has nothing to correlate
                assert _corr(d[ok, k], mmn[ok, k]) > 0.5, (scan.artifact, k, _corr(d[ok, k], mmn[ok, k]))


def test_the_one_place_flips_exactly() -> None:
    t = np.array([[1.5e-3, -2.0e-3, np.nan], [0.0, 3.0, -4.0]])
    d = published_deviation(t)
    np.testing.assert_array_equal(d[np.isfinite(t)], -t[np.isfinite(t)])
    assert np.isnan(d[0, 2])
    np.testing.assert_array_equal(study_target(d), t)
    f32 = published_deviation(t.astype(np.float32))
    assert f32.dtype == np.float32
    nan_bits = np.float32(np.nan).view(np.uint32)
    assert published_deviation(np.array([np.nan], np.float32)).view(np.uint32)[0] == nan_bits  # NaN untouched
