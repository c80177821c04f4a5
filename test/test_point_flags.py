"""The compiled per-point flags and decisions (judge/point_flags.py) give what the numpy composition of
judge/flags.py gives — angle, domain (range, multivariate, shape), normal quality, tolerance, invalid, no-U bits and
the ISO 14253-1 classes under both rules — on random kept points with NaN predictions, NaN U, NaN features and
values at the thresholds; the scatter into the cloud keeps the no-silent-NaN invariant; the point masks and base
flags are the numpy expressions they replace; bad inputs raise."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from xmetro_ros.judge import flags as fl
from xmetro_ros.judge.point_flags import NO_DECISION, base_flags, kept_point_flags, point_masks, scatter_kept
from xmetro_ros.scan.scan import Scan


def _numpy(pred, U, cos_i, cos_v, gi, gv, X, lo, hi, margin, nq, nq_min, tol, rule, mv, shape):
    """The composition ScanHandler.process used before the compiled pass (its order of operations)."""
    finite = np.isfinite(pred).all(axis=1)
    kf = fl.angle_flags(np.zeros_like(pred), pred, pred, gi, gv, cos_i=cos_i, cos_v=cos_v)
    kf |= fl.domain_flags(X, lo, hi, margin)
    if mv is not None:
        kf[mv] |= fl.FLAG_OUT_OF_DOMAIN | fl.FLAG_DOMAIN_MULTIVARIATE
    if shape is not None:
        kf[shape] |= fl.FLAG_OUT_OF_DOMAIN | fl.FLAG_DOMAIN_SHAPE
    kf[np.asarray(nq) < nq_min] |= fl.FLAG_UNRELIABLE_NORMAL
    dnorm = np.sqrt(np.einsum("ij,ij->i", pred, pred))
    kf[dnorm > tol] |= fl.FLAG_OVER_TOLERANCE
    kf[~finite] |= fl.FLAG_INVALID_POINT
    no_u = finite & ~np.isfinite(U).all(axis=1)
    kf[no_u] |= fl.FLAG_NO_UNCERTAINTY
    cls = np.full(len(pred), NO_DECISION, dtype=np.uint8)
    cls[finite] = fl.point_decisions(pred[finite], U[finite], tol, rule)
    kf[cls == fl.NON_CONFORMING] |= fl.FLAG_NON_CONFORMING
    kf[cls == fl.UNDECIDED] |= fl.FLAG_UNDECIDED
    return kf, cls


def _volume_mask(points: np.ndarray, half_width_mm: float) -> np.ndarray:
    """The working-volume mask ScanHandler.process computed before the compiled one (numpy)."""
    p = np.asarray(points).reshape(-1, 3)
    with np.errstate(invalid="ignore"):
        out = np.abs(p[:, 0]) > half_width_mm
        out |= np.abs(p[:, 1]) > half_width_mm
        out |= np.abs(p[:, 2]) > half_width_mm
    return out


def _case(seed: int, m: int, f: int, cos_dtype):
    rng = np.random.default_rng(seed)
    pred = rng.normal(0, 0.06, (m, 3))
    U = np.abs(rng.normal(0, 0.03, (m, 3)))
    pred[rng.random((m, 3)) < 0.05] = np.nan
    U[rng.random((m, 3)) < 0.05] = np.nan
    pred[rng.random(m) < 0.02] = [0.1, 0.0, 0.0]  # |d| exactly at the tolerance
    U[rng.random(m) < 0.02] = 0.0
    cos_i = rng.uniform(-0.2, 1, m).astype(cos_dtype)
    cos_v = rng.uniform(-0.2, 1, m).astype(cos_dtype)
    cos_i[:3] = np.cos(np.radians(75.0))  # at the grazing threshold
    X = rng.normal(0, 1, (m, f)).astype(np.float32)
    X[rng.random((m, f)) < 0.01] = np.nan
    lo, hi = np.full(f, -2.0), np.full(f, 2.0)
    X[m // 2, 0] = np.float32(-2.0 - 0.1 * 4.0)  # at the widened bound
    nq = rng.random(m).astype(np.float32)
    nq[:4] = np.float32(0.3)
    mv = rng.random(m) < 0.05
    shape = rng.random(m) < 0.05
    return pred, U, cos_i, cos_v, X, lo, hi, nq, mv, shape


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), m=st.integers(1, 3000), f=st.integers(1, 12),
       rule=st.sampled_from(fl.DECISION_RULES), cos64=st.booleans(), with_mv=st.booleans(),
       with_shape=st.booleans())
def test_compiled_flags_are_the_numpy_composition(seed, m, f, rule, cos64, with_mv, with_shape):
    pred, U, cos_i, cos_v, X, lo, hi, nq, mv, shape = _case(seed, m, f, np.float64 if cos64 else np.float32)
    mv_, shape_ = (mv if with_mv else None), (shape if with_shape else None)
    got_f, got_c = kept_point_flags(pred, U, cos_i, cos_v, 75.0, 70.0, X, lo, hi, 0.1, nq, 0.3, 0.1, rule,
                                    mv_ood=mv_, shape_ood=shape_)
    exp_f, exp_c = _numpy(pred, U, cos_i, cos_v, 75.0, 70.0, X, lo, hi, 0.1, nq, 0.3, 0.1, rule, mv_, shape_)
    np.testing.assert_array_equal(got_c, exp_c)
    np.testing.assert_array_equal(got_f, exp_f)


def test_each_out_of_domain_reason_sets_its_own_bit_with_out_of_domain():
    # five points: in domain; a feature beyond its widened range; multivariate only; shape only; all three
    X = np.array([[0.0], [3.0], [0.0], [0.0], [3.0]], np.float32)
    mv = np.array([False, False, True, False, True])
    shape = np.array([False, False, False, True, True])
    d = np.full((5, 3), 0.001)
    got, _ = kept_point_flags(d, d, np.ones(5), np.ones(5), 75.0, 70.0, X, np.array([-1.0]), np.array([1.0]), 0.05,
                              np.ones(5, np.float32), 0.3, 0.1, mv_ood=mv, shape_ood=shape)
    dom = got & (fl.FLAG_OUT_OF_DOMAIN | fl.DOMAIN_REASON_BITS)
    ood = fl.FLAG_OUT_OF_DOMAIN
    assert list(dom) == [0, ood | fl.FLAG_DOMAIN_FEATURES, ood | fl.FLAG_DOMAIN_MULTIVARIATE,
                         ood | fl.FLAG_DOMAIN_SHAPE, ood | fl.DOMAIN_REASON_BITS]
    # the reasons are detail bits: OUT_OF_DOMAIN alone makes a point unfit, and counts it once
    assert not fl.QUALITY_BITS & fl.DOMAIN_REASON_BITS
    assert fl.domain_flags(X, np.array([-1.0]), np.array([1.0]), 0.05)[1] == ood | fl.FLAG_DOMAIN_FEATURES


def test_scatter_puts_the_kept_points_in_cloud_order_and_flags_silent_nans():
    n = 10
    idx = np.array([7, 2, 5])
    pred = np.array([[0.01, 0, 0], [np.nan, 0, 0], [0.2, 0, 0]])
    U = np.full((3, 3), 0.01)
    kf = np.array([0, 0, fl.FLAG_OVER_TOLERANCE], np.uint16)
    cls = np.array([fl.CONFORMING, NO_DECISION, fl.NON_CONFORMING], np.uint8)
    flags = np.zeros(n, np.uint16)
    flags[0] = fl.FLAG_INVALID_POINT
    dev, unc, dec = scatter_kept(n, idx, pred, U, kf, cls, flags)
    np.testing.assert_array_equal(dev[7], pred[0])
    np.testing.assert_array_equal(dev[5], pred[2])
    assert np.isnan(dev[[0, 1, 3]]).all() and np.isnan(unc[0]).all() and (unc[idx] == 0.01).all()
    assert dec[7] == fl.CONFORMING and dec[5] == fl.NON_CONFORMING and dec[2] == NO_DECISION and dec[0] == NO_DECISION
    # a non-finite d and no flag (index 2 here, or a point no stage flagged) gets INVALID_POINT; a clean one stays 0
    assert flags[2] == fl.FLAG_INVALID_POINT and flags[1] == fl.FLAG_INVALID_POINT
    assert flags[7] == 0 and flags[5] == fl.FLAG_OVER_TOLERANCE and flags[0] == fl.FLAG_INVALID_POINT
    with pytest.raises(ValueError, match="outside the cloud"):
        scatter_kept(3, idx, pred, U, kf, cls, np.zeros(3, np.uint16))


def test_bad_inputs_raise():
    p = np.zeros((2, 3))
    args = (np.ones(2), np.ones(2), 75.0, 75.0, np.zeros((2, 1), np.float32), np.zeros(1), np.ones(1), 0.1,
            np.ones(2, np.float32), 0.5)
    with pytest.raises(ValueError, match="tolerance must be > 0"):
        kept_point_flags(p, p, *args, 0.0)
    with pytest.raises(ValueError, match="unknown decision rule"):
        kept_point_flags(p, p, *args, 0.1, "lenient")
    with pytest.raises(ValueError, match="U must be >= 0"):
        kept_point_flags(p, -np.ones((2, 3)), *args, 0.1)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 5000), f64=st.booleans(), hw=st.sampled_from([5.0, 1e3]))
def test_point_masks_and_base_flags_are_the_numpy_expressions(seed, n, f64, hw):
    """Finite and working-volume masks (NaN, ±inf, one bad coordinate, points at and beyond the volume's edge) and
    the flags built from them with outliers: those of ``Scan.valid_mask``, the numpy volume mask and the numpy OR-ing
    ScanHandler.process did."""
    rng = np.random.default_rng(seed)
    p = rng.normal(0, 4, size=(n, 3)).astype(np.float64 if f64 else np.float32)
    bad = rng.random((n, 3))
    p[bad < 0.05] = np.nan
    p[(bad >= 0.05) & (bad < 0.08)] = np.inf
    p[(bad >= 0.08) & (bad < 0.1)] = -np.inf
    p[(bad >= 0.1) & (bad < 0.12)] = hw  # on the edge: inside
    finite, outside, n_valid = point_masks(p, hw)
    want_f = Scan(points=p, settings=None, pose=None, scanner_id="").valid_mask()
    want_o = _volume_mask(p, hw)
    np.testing.assert_array_equal(finite, want_f)
    np.testing.assert_array_equal(outside, want_o)
    assert n_valid == int(np.count_nonzero(want_f & ~want_o))
    outlier = rng.choice(n, size=rng.integers(0, n + 1), replace=False)
    want = np.zeros(n, np.uint16)
    want[~want_f] |= fl.FLAG_INVALID_POINT
    want[want_o] |= fl.FLAG_OUT_OF_VOLUME
    want[outlier] |= fl.FLAG_OUTLIER
    np.testing.assert_array_equal(base_flags(finite, outside, outlier), want)
    with pytest.raises(ValueError, match="outlier index"):
        base_flags(finite, outside, np.array([n]))
