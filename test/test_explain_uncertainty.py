"""SHAP of the expanded uncertainty U (``attribution`` with ``output="uncertainty"``) on the shipped model set:
additive, and equal to ``ModelSet.predict_with_uncertainty``'s U, both for the in-cloud scheme (PointNet sets) and
for the plain scheme (``predict_batch``), which point-wise model sets use."""

from __future__ import annotations

import numpy as np
import pytest

from xmetro_ros.judge.attribution import explain, explain_in_cloud
from xmetro_ros.judge.features import FeatureContext, compute_features
from xmetro_ros.judge.inference import ModelSet
from xmetro_ros.preprocess import PreprocessConfig, prepare_scan
from xmetro_ros.scan.artifacts import Sphere
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings
from xmetro_ros.sim import simulate_scan


@pytest.fixture(scope="module")
def cloud():
    ms = ModelSet.load()
    scan = simulate_scan(Sphere(20.0, np.zeros(3)), ScanSettings(6.0, 3.0, 0.1), seed=31)
    prep = prepare_scan(scan, PreprocessConfig(), scanner=ScannerModel.load())
    X = compute_features(list(ms.feature_names), FeatureContext.from_prepared(prep), dtype=np.float32)
    X = X[np.isfinite(X).all(axis=1)][:3000]
    return ms, X


def test_in_cloud_shap_of_U_is_additive_and_equals_published_U(cloud):
    ms, X = cloud
    assert ms.calibrated and ms.has_sets
    rows = np.arange(0, len(X), 97)
    up = ms.predict_with_uncertainty(X)
    r = explain_in_cloud(ms, X, rows, output="uncertainty", max_background=3)
    np.testing.assert_allclose(r.base_values + r.shap.sum(axis=1), r.predictions, rtol=0, atol=1e-6)  # mm: 1e-9 m
    np.testing.assert_allclose(r.predictions, up.U[rows], rtol=0, atol=1e-6)
    assert r.feature_names[-1] == "set_context"
    # U is not the error: the explanation differs from that of d
    rd = explain_in_cloud(ms, X, rows, max_background=3)
    np.testing.assert_allclose(rd.predictions, up.errors[rows], rtol=0, atol=1e-6)
    assert not np.allclose(rd.shap, r.shap)
    with pytest.raises(ValueError, match="output"):
        explain_in_cloud(ms, X, rows, output="variance")


def test_plain_shap_of_U_through_predict_batch(cloud):
    ms, X = cloud
    Xs = X[:200]
    r = explain(ms, Xs, output="uncertainty", max_background=2)
    np.testing.assert_allclose(r.base_values + r.shap.sum(axis=1), r.predictions, rtol=0, atol=1e-6)
    np.testing.assert_allclose(r.predictions, ms.predict_with_uncertainty(Xs).U, rtol=0, atol=1e-6)


def test_shap_of_U_keeps_each_points_surface_class():
    """With a card calibrated per surface class, the explanation of U takes each point's class (the judge's) and its
    measured noise as a player: base + Σ SHAP equals the published per-class U, in a cloud and through
    predict_batch, with the same base as without classes (which explains the all-class U, different on this part);
    classes or noise of the wrong length are refused."""
    from xmetro_ros.parts.study import PRESENTATION
    from xmetro_ros.preprocess.curvature import principal_curvatures
    from xmetro_ros.preprocess.noise import noise_scale
    from xmetro_ros.scan.generated_parts import make_part

    ms = ModelSet.load()
    assert ms.by_surface and ms.noise_in_u
    scan = simulate_scan(make_part("bowl").transformed(PRESENTATION), ScanSettings(6.0, 3.0, 0.5), seed=4)
    prep = prepare_scan(scan, PreprocessConfig(), scanner=ScannerModel.load())
    X = compute_features(list(ms.feature_names), FeatureContext.from_prepared(prep), dtype=np.float32)
    cls = ms.surface_classes(principal_curvatures(prep))
    noise = noise_scale(prep)
    fin = np.isfinite(X).all(axis=1)
    X, cls, noise = X[fin][:3000], cls[fin][:3000], noise[fin][:3000]
    assert len(np.unique(cls[cls >= 0])) >= 2 and np.isfinite(noise).mean() > 0.9
    up = ms.predict_with_uncertainty(X, surface_class=cls, noise=noise)
    # the measured noise changes U here (it is the larger σ on some points)
    assert not np.array_equal(up.U, ms.predict_with_uncertainty(X, surface_class=cls).U)
    rows = np.arange(0, len(X), 97)
    r = explain_in_cloud(ms, X, rows, output="uncertainty", max_background=3, surface_class=cls, noise=noise)
    assert r.feature_names[-2:] == ["set_context", "surface_class"]
    np.testing.assert_allclose(r.base_values + r.shap.sum(axis=1), r.predictions, rtol=0, atol=1e-6)
    np.testing.assert_allclose(r.predictions, up.U[rows], rtol=0, atol=1e-6)
    plain = explain_in_cloud(ms, X, rows, output="uncertainty", max_background=3)
    assert plain.feature_names[-1] == "set_context" and not np.allclose(plain.predictions, r.predictions)
    # the same base for every point (the all-class multiplier with the class off): the class's share is the rest
    np.testing.assert_allclose(plain.base_values, r.base_values, rtol=0, atol=1e-9)
    assert np.abs(r.shap[:, -1]).max() > 1e-4
    rp = explain(ms, X[:200], output="uncertainty", max_background=2, surface_class=cls[:200], noise=noise[:200])
    assert rp.feature_names[-1] == "surface_class"
    np.testing.assert_allclose(rp.base_values + rp.shap.sum(axis=1), rp.predictions, rtol=0, atol=1e-6)
    np.testing.assert_allclose(rp.predictions, ms.predict_with_uncertainty(X[:200], surface_class=cls[:200],
                                                                           noise=noise[:200]).U, rtol=0, atol=1e-6)
    with pytest.raises(ValueError, match="surface classes"):
        explain_in_cloud(ms, X, rows, output="uncertainty", surface_class=cls[:10])
    with pytest.raises(ValueError, match="noise scales"):
        explain_in_cloud(ms, X, rows, output="uncertainty", surface_class=cls, noise=noise[:10])
