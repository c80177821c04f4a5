"""One-pass summary statistics (xmetro_ros.judge.scan_stats) equal the numpy computation the summary used before."""

from __future__ import annotations

import os

import numpy as np
import pytest

from xmetro_ros.judge import flags as fl
from xmetro_ros.judge import scan_stats as st
from xmetro_ros.judge.inference import ModelSet
from xmetro_ros.judge.scan_handler import HandlerParams, ScanHandler
from xmetro_ros.scan.artifacts import Sphere
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings
from xmetro_ros.sim import simulate_scan


def old_stats(pred: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The summary's previous computation (scan_handler.summarize before the compiled pass)."""
    a = np.abs(pred)
    mean = a.mean(axis=0) if len(a) else np.zeros(3)
    p95 = np.percentile(a, 95, axis=0) if len(a) else np.zeros(3)
    return mean, p95


def sample(rng: np.random.Generator, n: int, kind: str) -> np.ndarray:
    if kind == "normal":
        return rng.standard_normal((n, 3)) * 0.01
    if kind == "ties":  # few distinct values: many equal order statistics
        return rng.integers(-3, 4, (n, 3)) * 0.0125
    if kind == "sorted":
        return np.sort(rng.standard_normal((n, 3)), axis=0)
    return np.sort(rng.standard_normal((n, 3)), axis=0)[::-1].copy()  # reversed


@pytest.mark.parametrize("kind", ["normal", "ties", "sorted", "reversed"])
def test_mean_and_p95_equal_numpy(kind):
    rng = np.random.default_rng(len(kind))
    for n in (1, 2, 3, 19, 20, 21, 101, 1000, 4097, 180_001):
        pred = sample(rng, n, kind)
        mean, p95 = st.abs_error_stats(pred)
        m0, p0 = old_stats(pred)
        assert np.array_equal(mean, m0) and np.array_equal(p95, p0), n
        rows = rng.random(n) < 0.7
        mean, p95 = st.abs_error_stats(pred, rows)
        m0, p0 = old_stats(pred[rows])
        assert np.array_equal(mean, m0) and np.array_equal(p95, p0), n


def test_percentiles_and_empty():
    rng = np.random.default_rng(7)
    a = rng.standard_normal(5001)
    for q in (0.0, 1.0, 49.9, 50.0, 95.0, 99.99, 100.0):
        assert st.percentile_linear(a.copy(), q) == np.percentile(a, q)
    pred = rng.standard_normal((10, 3))
    for got, want in zip(st.abs_error_stats(pred, np.zeros(10, bool)), (np.zeros(3), np.zeros(3)), strict=True):
        assert np.array_equal(got, want)
    assert np.array_equal(st.abs_error_stats(np.zeros((0, 3)))[1], np.zeros(3))


def test_flag_tally_equals_flag_counts():
    rng = np.random.default_rng(3)
    for n in (0, 1, 1000, 200_000):
        flags = (rng.integers(0, 128, n) * (rng.random(n) < 0.3)).astype(np.uint16)
        n_flagged, counts = st.flag_tally(flags, fl.FLAG_BITS)
        assert n_flagged == int(np.count_nonzero(flags)) and counts == fl.flag_counts(flags)


def test_summary_of_a_judged_scan_equals_the_old_computation():
    model = ModelSet.load(os.environ.get("XMETRO_TEST_MODEL_DIR") or None)
    handler = ScanHandler(model, ScannerModel.load(), HandlerParams())
    assert handler.warm_up_s >= 0
    res = handler.process(simulate_scan(Sphere(17.5, np.zeros(3)), ScanSettings(10.0, 4.0, 0.5), seed=2))
    pred = res.predictions
    finite = np.isfinite(pred).all(axis=1)
    m0, p0 = old_stats(pred[finite])
    q = res.quality
    assert q["mean_abs_error_mm"] == [float(x) for x in m0] and q["p95_abs_error_mm"] == [float(x) for x in p0]
    assert q["flag_counts"] == fl.flag_counts(res.flags)
    # flagged valid points: every invalid point carries a flag (INVALID_POINT / OUT_OF_VOLUME)
    assert q["points_flagged"] == int(np.count_nonzero(res.flags)) - (q["points_received"] - q["points_valid"])
    # the same numbers through the old entry (pred already reduced to its finite rows)
    U = res.row_uncertainty
    no_u = ~np.isfinite(U).all(axis=1) if U is not None else np.zeros(len(pred), bool)
    again = handler.summarize(res.flags, pred[finite], q["points_valid"], False, False, q["points_received"],
                              U=None if U is None else U[finite & ~no_u], decisions=res.decisions[res.decisions != 255])
    assert again == q


@pytest.mark.parametrize("kind", ["normal", "ties", "sorted", "reversed", "constant", "heavy_tail"])
def test_sampled_bracket_percentile_is_the_full_selection(kind):
    """Columns of 20,000 values and more find their percentile from a sample's bracket: numpy's value at every q,
    with ties, a constant column, sorted input (a sample far off) and a heavy tail, at 1 and several threads."""
    import numba

    rng = np.random.default_rng(len(kind) + 3)
    for n in (20_000, 20_001, 166_269):
        if kind == "constant":
            a = np.full(n, 0.0125)
        elif kind == "heavy_tail":
            a = np.abs(rng.standard_cauchy(n))
        else:
            a = np.abs(sample(rng, n, kind)[:, 0])
        for q in (0.0, 0.01, 50.0, 95.0, 99.99, 100.0):
            for t in sorted({1, numba.config.NUMBA_NUM_THREADS}):
                got = float(st._percentile_sampled(a, q / 100, st.row_blocks(n, t)))
                assert got == np.percentile(a, q), (n, q, t)
