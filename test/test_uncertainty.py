"""Calibrated 95 % intervals (issue 14): a pointnet_multi with its spread head, trained in the test, calibrated by
split-conformal on held-out calibration clouds, judged on clouds of seeds AND artifacts never used in training or
calibration against the simulator's truth (Scan.noise_std): coverage per axis and per incidence / exposure bin,
sharpness against the oracle interval, rank correlation of U with the true spread; the multivariate domain."""

from __future__ import annotations

import json

import numpy as np
import onnxruntime as ort
import pytest

from xmetro_ros.calibrate.dataset import build_table
from xmetro_ros.judge.features import STUDY_FEATURES
from xmetro_ros.judge.inference import SIGMA_CAP_FACTOR, ModelLoadError, ModelSet
from xmetro_ros.learn.uncertainty import interval_metrics, predict_clouds
from xmetro_ros.learn.uncertainty_eval import bins_for, markdown, run
from xmetro_ros.scan.artifacts import Sphere
from xmetro_ros.scan.geometry import HeadPose, quat_to_matrix
from xmetro_ros.scan.scanner import ScannerModel
from xmetro_ros.sim import simulate_scan

SC = ScannerModel.load()
NAMES = list(STUDY_FEATURES)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """The acceptance experiment of xmetro_ros.learn.uncertainty_eval (train seed 1 / calibration seed 2, same
    artifacts, other clouds / test seed 3 on a 45 mm sphere and a 15 mm cylinder: artifacts in neither).
    ~1 min on the shared 2-core machine."""
    r = run(tmp_path_factory.mktemp("unc") / "m")
    return {"tr": r["train"], "cal": r["cal"], "te": r["test"], "dir": r["dir"], "ms": r["model_set"],
            "block": r["calibration"], "pred": r["pred"], "metrics": r["metrics"]}


def test_onnx_has_both_outputs_and_predict_is_unchanged(trained):
    ms, te = trained["ms"], trained["te"]
    sess = ort.InferenceSession(str(ms.members[0].path), providers=["CPUExecutionProvider"])
    assert [o.name for o in sess.get_outputs()] == ["y", "log_sigma"]
    rows = te.cloud_id == 0
    r = ms.predict_with_uncertainty(te.X[rows])
    np.testing.assert_array_equal(r.errors, ms.predict(te.X[rows]))  # same published predictions
    mult = ms.multipliers(te.X[rows])  # per condition (incidence x exposure); NaN: too few calibration points
    assert np.all(np.isfinite(r.U) == np.isfinite(mult)) and np.isfinite(mult).mean() > 0.9
    assert np.all(r.U[np.isfinite(mult)] > 0) and r.out_of_domain.dtype == bool
    floor = trained["block"]["sigma_floor_mm"]
    inside = ~r.out_of_domain
    np.testing.assert_allclose(r.U[inside], mult * (r.sigma[inside] + floor))
    if r.out_of_domain.any():  # widened by distance / threshold outside
        out = r.out_of_domain
        np.testing.assert_allclose(r.U[out], mult * (r.sigma[out] + floor) * r.domain_distance[out, None])


def test_card_records_the_calibration(trained):
    card = json.loads((trained["dir"] / "card.json").read_text())
    u = card["uncertainty"]
    assert "split-conformal" in u["method"] and "crepes" in u["method"]
    assert len(u["calibration_clouds"]) == len(trained["cal"].clouds)
    assert u["calibration_clouds"][0].startswith("seed2/")
    assert len(u["multiplier"]) == 3 and all(1.0 < k < 4.0 for k in u["multiplier"])
    for ax in "xyz":  # finite-sample conformal quantile: at least the level, barely above it on ~20k points
        assert 0.95 <= u["achieved_coverage_calibration"][ax] < 0.952
    assert card["domain_mv"]["threshold"] > 0
    # σ̂'s ceiling is twice the largest σ̂ on the calibration clouds (it caps nothing there)
    cal = trained["cal"]
    sig = predict_clouds(trained["ms"], cal.X, cal.cloud_id, with_u=False)["sigma"]
    np.testing.assert_allclose(np.nanmax(sig, axis=0), u["sigma_max_mm"], rtol=1e-5)


def test_sigma_is_capped_far_outside_the_data(trained):
    """Far outside the data the spread head extrapolates exponentially (float32 exp overflows to inf on a scene in
    metres read as millimetres); σ̂ stops at the calibration's largest and the domain distance alone widens U."""
    ms, te = trained["ms"], trained["te"]
    X = te.X[te.cloud_id == 0] * np.float32(50.0)
    with np.errstate(over="raise", invalid="raise"):
        r = ms.predict_with_uncertainty(X)
    smax = SIGMA_CAP_FACTOR * np.asarray(ms.card["uncertainty"]["sigma_max_mm"])
    assert r.out_of_domain.all() and np.all(r.sigma <= smax * (1 + 1e-5)) and np.any(r.sigma >= smax * (1 - 1e-5))
    mult, floor = ms.multipliers(X), ms.card["uncertainty"]["sigma_floor_mm"]
    assert np.all(np.isfinite(r.U) == np.isfinite(mult))
    np.testing.assert_allclose(r.U, mult * (r.sigma + floor) * r.domain_distance[:, None], rtol=1e-6)


def test_coverage_sharpness_and_rank_on_new_seeds_and_artifacts(trained):
    te, p = trained["te"], trained["pred"]
    names = NAMES
    bins = bins_for(te.X, names)
    inc_deg = bins["incidence_deg"][0]
    met = interval_metrics(p["errors"], p["U"], te.y, te.oracle_std, bins=bins)
    assert met == trained["metrics"]
    print("\n" + markdown(met, trained["block"]))  # the docs table (pytest -s)
    for ax, m in met.items():
        assert m["n"] > 10_000, ax
        # One training realization: its trajectory depends on the CPU's float kernels (same code and seeds gave
        # X/Y/Z 95.35 / 94.27 / 95.29 % on one machine, 96.06 / 93.93 / 95.39 % on an AMD EPYC, X 97.06 % on an
        # Intel Xeon with AVX-512; docs/uncertainty.md), so the fresh model is held to 93-97.5 %; the published
        # intervals' 94-96 % is asserted on the shipped model set (test_shipped_default_intervals_on_new_seeds_and_
        # artifacts).
        assert 0.93 <= m["coverage"] <= 0.975, (ax, m["coverage"])
        assert m["sharpness_ratio"] <= 1.3, (ax, m["sharpness_ratio"])
        assert m["spearman_U_true_std"] >= 0.7, (ax, m["spearman_U_true_std"])
        for name, rows in m["bins"].items():
            for b in rows:
                if b["n"] >= 200:  # bins with enough points to measure a coverage
                    assert b["coverage"] >= 0.90, (ax, name, b)
        assert sum(b["n"] >= 200 for b in m["bins"]["incidence_deg"]) >= 4
        assert sum(b["n"] >= 200 for b in m["bins"]["exposure_ms"]) == 3
    # A point the simulator makes noisy (grazing incidence, short exposure) gets a larger U than a benign one.
    z = 2
    noisy = (inc_deg > 60) & (te.X[:, names.index("exposure_time")] < 0.2)
    benign = (inc_deg < 30) & (te.X[:, names.index("exposure_time")] > 1.0)
    assert np.median(p["U"][noisy, z]) > 1.5 * np.median(p["U"][benign, z])


def test_multivariate_domain_flags_far_pose_not_training(trained):
    ms, tr = trained["ms"], trained["tr"]
    assert ms.out_of_domain_mv(tr.X).mean() <= 0.002  # the 99.9 % quantile of the training distances
    assert ms.out_of_domain_mv(trained["te"].X).mean() < 0.01  # new artifacts and seeds, same poses: inside
    settings = SC.study_configurations()[13]
    start = HeadPose.looking_down(90.0, y_mm=-35.0)
    tilt = start.rotated(quat_to_matrix([np.sin(np.radians(20)), 0, 0, np.cos(np.radians(20))]), pivot=np.zeros(3))
    for pose, want_min in ((None, None), (tilt, 0.9)):
        scan = simulate_scan(Sphere(22.5), settings, scanner=SC, pose=pose, seed=11)
        X = build_table([scan], NAMES, max_points_per_cloud=None).X
        frac = ms.out_of_domain_mv(X).mean()
        if want_min is None:
            assert frac < 0.01
        else:
            assert frac >= want_min  # a head tilted 40 deg about its X axis: training never saw it
            r = ms.predict_with_uncertainty(X)
            out = r.out_of_domain
            base = ms.multipliers(X)[out] * (r.sigma[out] + 0.001)
            cal = np.isfinite(base)  # a point of a condition the calibration had too few points of has no U
            assert cal.mean() > 0.9 and np.all(np.isnan(r.U[out][~cal]))
            assert np.all(r.U[out][cal] > base[cal])  # widened outside the domain
            assert np.median(r.domain_distance[out]) > 1.0


def test_uncalibrated_model_set_refuses_uncertainty(tmp_path, trained):
    import shutil

    d = tmp_path / "m"
    shutil.copytree(trained["dir"], d)
    card = json.loads((d / "card.json").read_text())
    del card["uncertainty"]
    (d / "card.json").write_text(json.dumps(card))
    ms = ModelSet.load(d)
    assert not ms.calibrated
    with pytest.raises(ModelLoadError, match="no uncertainty calibration"):
        ms.predict_with_uncertainty(trained["te"].X[:10])
    ms.predict(trained["te"].X[:10])  # predict works as before


def test_card_without_multivariate_domain_falls_back_to_min_max(trained, tmp_path):
    import shutil

    d = tmp_path / "m"
    shutil.copytree(trained["dir"], d)
    card = json.loads((d / "card.json").read_text())
    del card["domain_mv"]
    (d / "card.json").write_text(json.dumps(card))
    ms = ModelSet.load(d)
    X = trained["te"].X[:500]
    np.testing.assert_array_equal(ms.out_of_domain_mv(X), ms.out_of_domain(X))
    assert np.isnan(ms.domain_distance(X)).all()
    r = ms.predict_with_uncertainty(X)  # no widening without the domain
    np.testing.assert_allclose(r.U, ms.multipliers(X) * (r.sigma + card["uncertainty"]["sigma_floor_mm"]))


def test_shipped_default_intervals_on_new_seeds_and_artifacts():
    """The packaged default (full profile, calibrated on campaign seed 1000 and the calibration surfaces) on a Ø40
    sphere and an r 15 mm cylinder simulated with seed 3, each point's U of its surface class as the node publishes
    it, on the scan's measured noise (docs/uncertainty.md table). Calibrated per condition (incidence × exposure)
    with the envelope over neighbouring incidence bins, every bin covers ≥ 93 % (one multiplier per axis: 91.5 % in
    the worst); overall 95.7-95.9 % with U 1.04-1.06× the oracle half-width (on σ̂ alone, 0.7.3-0.7.4: 96.3-97.1 %,
    1.10-1.16×: holding on parts then cost width on spheres)."""
    from xmetro_ros.learn.uncertainty_eval import evaluate_shipped

    r = evaluate_shipped()
    u = r["calibration"]
    assert "crepes" in u["method"] and len(u["calibration_clouds"]) == 216 and u["conditional"]["by_surface"]["noise"]
    assert r["per_class"] and (r["surface_class"] == 1).mean() > 0.8  # spheres and a cylinder: mostly convex
    for ax, m in r["metrics"].items():
        assert 0.94 <= m["coverage"] <= 0.975, (ax, m["coverage"])
        assert m["sharpness_ratio"] <= 1.1 and m["spearman_U_true_std"] >= 0.7, (ax, m)
        for name, rows in m["bins"].items():
            assert all(b["coverage"] >= 0.93 for b in rows if b["n"] >= 200), (ax, name, rows)
