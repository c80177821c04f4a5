"""ISO 14253-1 decision rules (flags.decision_classes): each class follows its definition, including the edges."""

from __future__ import annotations

import numpy as np
import pytest

from xmetro_ros.judge.flags import CONFORMING, NON_CONFORMING, UNDECIDED, decision_classes


def test_guard_banded_classes_and_edges():
    tol = 0.05
    d = np.array([0.0, 0.03, -0.03, 0.04, 0.08, -0.08, 0.06, 0.02, 0.07, np.nan, 0.01])
    U = np.array([0.01, 0.02, 0.02, 0.02, 0.02, 0.02, 0.02, 0.03, 0.02, 0.01, np.nan])
    got = decision_classes(d, U, tol)
    # |d|+U<=tol: 0.01, 0.05 (edge), 0.05 (edge, sign ignored); 0.06 undecided; |d|-U = 0.06, 0.06 > tol;
    # 0.04 not > tol → undecided; 0.02+0.03 = 0.05 conforming (edge); 0.07-0.02 = 0.05 not > tol → undecided.
    want = [CONFORMING, CONFORMING, CONFORMING, UNDECIDED, NON_CONFORMING, NON_CONFORMING, UNDECIDED, CONFORMING,
            UNDECIDED, UNDECIDED, UNDECIDED]
    assert got.tolist() == want
    assert got.dtype == np.uint8


def test_simple_acceptance_ignores_U():
    d = np.array([[0.01, -0.05, 0.051], [np.nan, 0.0, -0.2]])
    got = decision_classes(d, np.full(d.shape, 1.0), 0.05, rule="simple")
    assert got.tolist() == [[CONFORMING, CONFORMING, NON_CONFORMING], [UNDECIDED, CONFORMING, NON_CONFORMING]]


def test_bad_arguments():
    with pytest.raises(ValueError, match="unknown decision rule"):
        decision_classes(np.zeros(2), np.zeros(2), 0.1, rule="lenient")
    with pytest.raises(ValueError, match="tolerance"):
        decision_classes(np.zeros(2), np.zeros(2), 0.0)
    with pytest.raises(ValueError, match="U must be"):
        decision_classes(np.zeros(2), np.array([0.1, -0.1]), 0.1)


def test_guard_banded_matches_definition_and_is_stricter_than_simple():
    rng = np.random.default_rng(7)
    d = rng.uniform(-1, 1, 5000)
    U = rng.uniform(0, 0.5, 5000)
    tol = rng.uniform(0.001, 0.5, 5000)
    g = decision_classes(d, U, tol)
    s = decision_classes(d, U, tol, rule="simple")
    want = np.where(np.abs(d) + U <= tol, CONFORMING, np.where(np.abs(d) - U > tol, NON_CONFORMING, UNDECIDED))
    np.testing.assert_array_equal(g, want)
    np.testing.assert_array_equal(s, np.where(np.abs(d) <= tol, CONFORMING, NON_CONFORMING))
    decided = g != UNDECIDED  # a guard-banded decision never contradicts simple acceptance
    np.testing.assert_array_equal(g[decided], s[decided])
    assert decided.mean() > 0.3 and (~decided).mean() > 0.1  # both happen in this draw
