"""The profile model (learn.profile_model) and its ONNX model set (judge.profile_model_set) on synthetic tables
whose truth is known: a deviation that depends on incidence, a per-position systematic offset shared by the
repeats, and noise."""

from __future__ import annotations

import json

import numpy as np
import pytest

from xmetro_ros.judge.profile_model_set import ProfileModelError, ProfileModelSet
from xmetro_ros.learn.profile_model import MIN_BIN_POINTS, ProfileModel, angle_bins

FEATURES = ["u", "w", "inc_plane", "arc_curvature"]


def _table(n_pos=80, reps=3, per=120, pos_sigma=0.020, noise=0.003, seed=0):
    """Rows of ``n_pos`` positions × ``reps`` repeats; deviation (mm) = 5 µm·sin(inc) + offset(position) + noise."""
    rng = np.random.default_rng(seed)
    X, y, pos = [], [], []
    for p in range(n_pos):
        off = rng.normal(0, pos_sigma)
        u0 = rng.uniform(-10, 10)
        inc = np.linspace(-65, 65, per)
        for _ in range(reps):
            X.append(np.column_stack([u0 + 10 * np.sin(np.radians(inc)), 250 + 0 * inc, inc, np.full(per, 1 / 15)]))
            y.append(0.005 * np.sin(np.radians(inc)) + off + rng.normal(0, noise, per))
            pos.append(np.full(per, p))
    return np.vstack(X).astype(np.float32), np.concatenate(y), np.concatenate(pos)


def test_u_is_the_width_at_a_new_position_not_at_a_repeat():
    """Repeats share their offset (σ 20 µm) and differ by 3 µm of noise: U calibrated on repeats of training
    positions would be ~6 µm; on positions the model never saw it must cover the offsets (≈ 40 µm), and it
    holds at ~95 % on positions of another draw."""
    X, y, pos = _table()
    m = ProfileModel(iterations=60, depth=4, folds=4).fit(X, y, pos, feature_names=FEATURES)
    hw = m.half_width_mm_
    assert hw is not None and np.all(hw[:7] > 0.030), hw
    Xn, yn, _ = _table(seed=1)
    cov = np.mean(np.abs(yn - m.predict(Xn)) <= m.uncertainty(Xn))
    assert 0.90 <= cov <= 0.99, cov


def test_bins_without_points_are_nan_and_thin_bins_borrow():
    X, y, pos = _table(n_pos=20, reps=2, per=60)
    m = ProfileModel(iterations=30, depth=3, folds=4).fit(X, y, pos, feature_names=FEATURES)
    counts = m.bin_counts_
    assert counts is not None and counts[7] == 0 and counts[8] == 0
    assert np.isnan(m.half_width_mm_[7]) and np.isnan(m.uncertainty(np.array([[0, 250, 85.0, 0.1]]))[0])
    thin = [b for b in range(7) if 0 < counts[b] < MIN_BIN_POINTS]
    for b in thin:
        assert m.bin_source_[b] == "envelope of neighbours"
    assert list(angle_bins(np.array([-5.0, 9.99, 10.0, 89.0, 95.0]))) == [0, 0, 1, 8, 8]


def test_fit_refuses_bad_input():
    X, y, pos = _table(n_pos=6, reps=1, per=10)
    with pytest.raises(ValueError, match="positions"):
        ProfileModel(folds=8).fit(X, y, pos)
    y2 = y.copy()
    y2[0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        ProfileModel(folds=2).fit(X, y2, pos)
    with pytest.raises(ValueError, match="must agree"):
        ProfileModel(folds=2).fit(X, y[:-1], pos)


def test_exported_model_set_runs_in_onnx_runtime(tmp_path):
    X, y, pos = _table(n_pos=30, reps=2, per=60)
    m = ProfileModel(iterations=80, depth=4, folds=3).fit(X, y, pos, feature_names=FEATURES)
    m.export(tmp_path / "ms", X[:500], extra_card={"scanner": {"id": "t"}})
    card = json.loads((tmp_path / "ms" / "card.json").read_text())
    assert card["onnx_check"]["max_abs_diff_mm"] < 1e-6 and card["scanner"]["id"] == "t"
    ms = ProfileModelSet(tmp_path / "ms")
    np.testing.assert_allclose(ms.predict(X), m.predict(X), atol=1e-6)
    np.testing.assert_array_equal(ms.uncertainty(X), m.uncertainty(X))
    assert ms.in_domain(X).all()
    far = X[:3].copy()
    far[:, 1] = -30.0  # a range the calibration never saw
    assert not ms.in_domain(far).any()
    d, U, ood = ms.publish(np.vstack([X[:2], far]))
    assert list(ood) == [False, False, True, True, True]
    assert np.isfinite(d[:2]).all() and np.isnan(d[2:]).all() and np.isnan(U[2:]).all()
    # Out of the domain, and in a bin never calibrated.
    d, U, ood = ms.publish(np.array([[0.0, 250.0, 85.0, 1 / 15]], np.float32))
    assert np.isnan(d[0]) and np.isnan(U[0])
    n = np.array([[0.6, 0.8], [-1.0, 0.0]])
    np.testing.assert_allclose(ms.per_axis(np.array([1.0, 2.0]), n), [[0.6, 0, 0.8], [-2.0, 0, 0]])
    np.testing.assert_allclose(ms.per_axis(np.array([1.0, 2.0]), n, absolute=True), [[0.6, 0, 0.8], [2.0, 0, 0]])
    with pytest.raises(ValueError, match=r"\(M, 4\)"):
        ms.predict(X[:, :3])
    with pytest.raises(ValueError, match="non-finite"):
        ms.predict(np.full((1, 4), np.nan, np.float32))


def test_model_set_errors(tmp_path):
    with pytest.raises(ProfileModelError, match=r"card\.json"):
        ProfileModelSet(tmp_path)
    (tmp_path / "card.json").write_text(json.dumps({"format": "xmetro-model/1"}))
    with pytest.raises(ProfileModelError, match="format"):
        ProfileModelSet(tmp_path)
    (tmp_path / "card.json").write_text(json.dumps({"format": "xmetro-profile-model/1", "features": FEATURES,
                                                    "uncertainty": {"half_width_mm": [0.05] * 9}}))
    with pytest.raises(ProfileModelError, match=r"model\.onnx"):
        ProfileModelSet(tmp_path)
