"""Principal curvatures of scanned surfaces against known shapes, the surface classes built on them, the shape
domain in the (κmin, κmax) plane, and U per surface class (judge/surface_class.py, preprocess/curvature.py,
learn/shape_domain.py, judge/conditions.py, the compiled U kernel)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as hst
from hypothesis.extra import numpy as hnp

from xmetro_ros.judge.conditions import condition_index, multiplier_table, row_multipliers
from xmetro_ros.judge.set_kernels import expand_u_conditional
from xmetro_ros.judge.surface_class import (
    SURFACE_CLASSES,
    card_surface_class,
    out_of_principal_domain,
    principal_domain_grid,
    surface_class,
)
from xmetro_ros.learn.shape_domain import fit_principal_domain
from xmetro_ros.learn.uncertainty import conditional_multipliers
from xmetro_ros.preprocess import prepare_scan
from xmetro_ros.preprocess.curvature import grid_principal_curvatures, principal_curvatures
from xmetro_ros.scan.artifacts import Cylinder, Plane, Sphere
from xmetro_ros.scan.calibration_surfaces import make_surface, surface_campaign, surface_presentation
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings
from xmetro_ros.sim import simulate_scan

SC = ScannerModel.load()
DEFAULT = ScanSettings(10.0, 4.0, 0.5)


def _kappa(artifact, settings=DEFAULT, seed=0):
    prep = prepare_scan(simulate_scan(artifact, settings, scanner=SC, seed=seed), scanner=SC)
    return prep, principal_curvatures(prep)


@pytest.mark.parametrize("artifact, kmin, kmax", [(Sphere(17.5), 1 / 17.5, 1 / 17.5), (Cylinder(20.0), 0.0, 1 / 20),
                                                  (Plane(), 0.0, 0.0)])
def test_principal_curvatures_of_known_shapes(artifact, kmin, kmax) -> None:
    """Medians within 0.008 /mm of the true principal curvatures (the fit's spread, never negative, pushes κmin
    down and κmax up by ~0.004 /mm at 0.5 ms); their mean within 3 % (or 0.001 /mm) of the true mean curvature."""
    _, k = _kappa(artifact)
    ok = np.isfinite(k).all(1)
    assert ok.mean() > 0.95
    med = np.median(k[ok], axis=0)
    assert abs(med[0] - kmin) < 0.008 and abs(med[1] - kmax) < 0.008, med
    assert abs(np.median(k[ok].mean(1)) - 0.5 * (kmin + kmax)) <= max(0.03 * 0.5 * (kmin + kmax), 0.001)
    assert (k[ok, 0] <= k[ok, 1]).all()


def test_saddle_reads_opposite_signs_and_the_classes_follow() -> None:
    """The calibration saddle (±1/30 /mm at its centre, tilted 20°) reads κmin < 0 < κmax near its centre and is
    mostly class saddle there; a plate is mostly flat, a sphere convex, a groove's floor concave; an unorganized
    scan has no curvature and no class."""
    sad = make_surface("saddle").transformed(surface_presentation((20.0, 0.0)))
    prep, k = _kappa(sad)
    p = np.asarray(prep.points)
    c = np.array([0.29, 0.17, 12.0])
    near = np.linalg.norm(p[:, :2] - c[:2], axis=1) < 6.0
    med = np.nanmedian(k[near], axis=0)
    assert med[0] < -0.025 and med[1] > 0.025, med
    assert np.mean(surface_class(k[near]) == SURFACE_CLASSES.index("saddle")) > 0.8
    for art, name, share in ((make_surface("plate"), "flat", 0.85), (Sphere(22.5), "convex", 0.95)):
        _, kk = _kappa(art)
        assert np.mean(surface_class(kk) == SURFACE_CLASSES.index(name)) > share, name
    grv = make_surface("groove").transformed(surface_presentation((0.0, 0.0)))
    prep, kk = _kappa(grv)
    pts = np.asarray(prep.points)
    floor = (np.abs(pts[:, 1] - (-8.0 + 0.17)) < 3.0) & (np.abs(pts[:, 0]) < 15.0)
    assert np.mean(surface_class(kk[floor]) == SURFACE_CLASSES.index("concave")) > 0.8
    flat = grid_principal_curvatures(pts, np.asarray(prep.normals), np.arange(len(prep)), (len(prep),), 6.0, 3.0)
    assert np.isnan(flat).all() and (surface_class(flat) == -1).all()


def test_surface_class_thresholds() -> None:
    """Flat within ±0.02 /mm, sharp beyond 0.1 /mm either way whatever the signs; a card calibrated with four
    classes classifies with its own thresholds and no sharp class; unknown classes are refused."""
    k = np.array([[0.0, 0.01], [0.0, 0.05], [-0.05, 0.0], [-0.05, 0.05], [np.nan, 0.0], [-0.02, 0.02],
                  [0.0, 0.5], [-0.3, 0.0], [-0.2, 0.05], [0.05, 0.1]])
    assert surface_class(k).tolist() == [0, 1, 2, 3, -1, 0, 4, 4, 4, 1]
    assert surface_class(k, sharp=None).tolist() == [0, 1, 2, 3, -1, 0, 1, 2, 3, 1]
    four = {"classes": ["flat", "convex", "concave", "saddle"], "flat_curvature_per_mm": 0.02}
    assert card_surface_class(k, four).tolist() == [0, 1, 2, 3, -1, 0, 1, 2, 3, 1]
    five = {**four, "classes": list(SURFACE_CLASSES), "sharp_curvature_per_mm": 0.4}
    assert card_surface_class(k, five).tolist() == [0, 1, 2, 3, -1, 0, 4, 2, 3, 1]
    with pytest.raises(ValueError, match="surface classes"):
        card_surface_class(k, {**four, "classes": ["flat", "edge"]})


_EDGY = hst.one_of(hst.floats(-1.0, 1.0), hst.sampled_from([np.nan, np.inf, -np.inf, 0.02, -0.02, 0.1, -0.1, 0.0]))


@settings(max_examples=150, deadline=None)
@given(hnp.arrays(np.float64, hst.tuples(hst.integers(1, 40), hst.just(2)), elements=_EDGY),
       hst.sampled_from([0.1, 0.4, None]))
def test_compiled_classes_are_the_rule_written_in_numpy(kappa, sharp) -> None:
    """The compiled classes (one pass) against the rule as numpy masks: finite rows only, flat within ±t (κmax ≤ t
    and κmin ≥ −t), convex / concave / saddle by which side crosses, sharp where max |κ| > s overrides."""
    lo, hi = kappa[:, 0], kappa[:, 1]
    want = np.full(len(kappa), -1, np.int8)
    with np.errstate(invalid="ignore"):
        up, down, ok = hi > 0.02, lo < -0.02, np.isfinite(lo) & np.isfinite(hi)
        want[ok & ~up & ~down], want[ok & up & ~down], want[ok & ~up & down], want[ok & up & down] = 0, 1, 2, 3
        if sharp is not None:
            want[ok & (np.maximum(np.abs(lo), np.abs(hi)) > sharp)] = 4
    got = surface_class(kappa, 0.02, sharp)
    assert got.dtype == np.int8 and got.tolist() == want.tolist()


@settings(max_examples=150, deadline=None)
@given(hnp.arrays(np.float64, hst.tuples(hst.integers(1, 30), hst.just(2)),
                  elements=hst.one_of(hst.floats(-1.0, 1.0), hst.sampled_from([np.nan, np.inf, -np.inf, 1e300, -0.4,
                                                                           0.4, 0.0]))),
       hnp.arrays(np.bool_, hst.tuples(hst.integers(1, 12), hst.integers(1, 12)).map(lambda t: (t[0], t[0]))))
def test_principal_domain_check_is_the_documented_rule(kappa, grid) -> None:
    """The compiled check against the rule written out in numpy: flagged = finite (κmin, κmax) whose cell
    floor((κ − lo) / bin) is off the grid or unoccupied; NaN / inf curvature never flagged."""
    lo, b = -0.4, 0.8 / grid.shape[0]
    ok = np.isfinite(kappa).all(axis=1)
    with np.errstate(invalid="ignore"):
        ij = np.floor((kappa - lo) / b)
    inside = ok & (ij >= 0).all(axis=1) & (ij < grid.shape[0]).all(axis=1)
    hit = np.zeros(len(kappa), bool)
    hit[inside] = grid[ij[inside, 0].astype(np.int64), ij[inside, 1].astype(np.int64)]
    assert out_of_principal_domain(kappa, grid, lo, b).tolist() == (ok & ~hit).tolist()


def test_principal_domain_keeps_what_calibration_saw_and_flags_the_rest() -> None:
    """Cells occupied by the calibration points (less the sparsest 0.1 %, grown by one cell) are in; a saddle point
    far from any calibration point is out; a NaN curvature is never flagged."""
    rng = np.random.default_rng(0)
    sph = np.column_stack([rng.normal(0.04, 0.005, 50_000)] * 2)
    pln = rng.normal(0.0, 0.006, (50_000, 2))
    dom = fit_principal_domain([np.sort(sph, axis=1), np.sort(pln, axis=1)])
    grid, lo, b = principal_domain_grid(dom)
    q = np.array([[0.04, 0.04], [0.0, 0.005], [-0.05, 0.05], [0.3, 0.35], [np.nan, np.nan], [5.0, 5.0]])
    assert out_of_principal_domain(q, grid, lo, b).tolist() == [False, False, True, True, False, True]
    assert dom["n"] == 100_000
    with pytest.raises(ValueError):
        fit_principal_domain([np.full((3, 2), np.nan)])


def _block(with_classes: bool):
    """A conditional calibration of synthetic rows: the score's spread is 1 on classes 0-2 and 3 on class 3, so
    the class-3 multiplier is ~3x the others."""
    rng = np.random.default_rng(1)
    m = 40_000
    names = ["Inc", "exposure_time"]
    X = np.column_stack([rng.uniform(0.05, 1.0, m), rng.choice([0.1, 0.5, 2.0], m)]).astype(np.float32)
    cls = rng.integers(-1, 5, m).astype(np.int8)
    sig = np.ones((m, 3))
    res = rng.normal(0.0, 1.0, (m, 3)) * np.where(cls == 3, 3.0, 1.0)[:, None]
    cond = conditional_multipliers(X, names, res, sig, np.ones((m, 3), bool),
                                   surface_class=cls if with_classes else None)
    return {"multiplier": [1.0, 1.0, 1.0], "conditional": cond}, X, names, cls


def test_each_sigma_source_of_a_class_cell_is_covered_on_its_own() -> None:
    """Per-class multipliers on σ = max(σ̂, noise·|N|): in each cell, the rows where the noise term is the larger
    (here it overstates their spread 2×) and those where σ̂ is (true to scale) are each covered at 95 %. Pooled, the
    multiplier fell to ~1.65 and left the σ̂ rows at ~90 %; per group it is the σ̂ rows' ~1.96."""
    rng = np.random.default_rng(4)
    m = 60_000
    names = ["Inc", "exposure_time"]
    X = np.column_stack([rng.uniform(0.05, 1.0, m), np.full(m, 0.5)]).astype(np.float32)
    cls = np.zeros(m, np.int8)
    sig_hat = np.ones((m, 3))
    noisy = rng.random(m) < 0.5
    surf = np.where(noisy[:, None], 2.0, 1.0) * np.ones((1, 3))  # noise term 2: the larger, and twice the spread
    res = rng.normal(0.0, 1.0, (m, 3))
    ok = np.ones((m, 3), bool)
    cond = conditional_multipliers(X, names, res, sig_hat, ok, surface_class=cls, surface_sigma=surf,
                                   noise_block={"window_cells": 7}, by_source=True)
    by = cond["by_surface"]
    idx = condition_index(X, names, cond["incidence_edges_deg"], cond["exposure_edges_ms"])
    k = np.array([[np.nan if v is None else v for v in by["own_multiplier"][0][c]] for c in idx])
    hit = np.abs(res) <= k * surf
    assert hit[~noisy].mean() > 0.94 and hit[noisy].mean() > 0.99
    assert 1.8 < np.nanmedian(k) < 2.2 and "sources" in by
    pooled = conditional_multipliers(X, names, res, surf, ok, surface_class=cls)["by_surface"]  # no source groups
    kp = np.array([[np.nan if v is None else v for v in pooled["own_multiplier"][0][c]] for c in idx])
    assert (np.abs(res) <= kp * surf)[~noisy].mean() < 0.92


def test_u_per_surface_class_and_the_compiled_kernel_agree() -> None:
    """Per-class multipliers follow each class's spread; a class's missing cell takes the all-class one; the
    compiled kernel gives the same bits as the Python lookup, with and without classes; a card without classes
    ignores them."""
    block, X, names, cls = _block(True)
    by = block["conditional"]["by_surface"]
    assert by["classes"] == list(SURFACE_CLASSES)
    per = [np.nanmean(np.array([[np.nan if v is None else v for v in c] for c in by["multiplier"][k]], float))
           for k in range(4)]
    assert per[3] > 2.5 * max(per[:3]) and 1.7 < per[0] < 2.3
    table = multiplier_table(block)
    n_cells = len(block["conditional"]["multiplier"])
    assert table.shape == ((1 + len(SURFACE_CLASSES)) * n_cells, 3)
    rows = row_multipliers(block, X, names, cls)
    cos_e = np.cos(np.radians(np.arange(10.0, 90.0, 10.0)))
    exp_e = np.array(block["conditional"]["exposure_edges_ms"][1:-1])
    sig = np.abs(np.random.default_rng(2).normal(0.002, 0.001, (len(X), 3)))
    dist = np.full(len(X), np.nan)
    u = expand_u_conditional(sig, 0.001, table, cos_e, exp_e, X[:, 0], X[:, 1], dist, cls)
    np.testing.assert_array_equal(u, (sig + 0.001) * rows)
    u0 = expand_u_conditional(sig, 0.001, table, cos_e, exp_e, X[:, 0], X[:, 1], dist)
    np.testing.assert_array_equal(u0, (sig + 0.001) * row_multipliers(block, X, names))
    # a class cell without its own multiplier takes the all-class one
    by["multiplier"][2][0] = [None, None, None]
    np.testing.assert_array_equal(multiplier_table(block)[3 * n_cells], multiplier_table(block)[0])
    plain, X2, _, cls2 = _block(False)
    assert "by_surface" not in plain["conditional"]
    np.testing.assert_array_equal(row_multipliers(plain, X2, names, cls2), row_multipliers(plain, X2, names))
    with pytest.raises(ValueError, match="surface classes"):
        expand_u_conditional(sig, 0.001, table[:n_cells], cos_e, exp_e, X[:, 0], X[:, 1], dist, cls)


def test_surface_campaign_spans_the_classes() -> None:
    """Every surface under every 13th setting (12 scans: all three exposures), each setting with another tilt; all
    five classes present in the campaign's points."""
    items = surface_campaign(SC, 0, stride=13)
    assert {st.exposure_ms for _, st, _, _ in items} == {0.1, 0.5, 2.0}
    assert len(items) == 12 and len({lab for *_, lab in items}) == 12
    seen = np.zeros(len(SURFACE_CLASSES), int)
    for art, st, seed, _ in items[::3]:
        prep = prepare_scan(simulate_scan(art, st, scanner=SC, seed=seed), scanner=SC)
        c = surface_class(principal_curvatures(prep))
        seen += np.bincount(c[c >= 0], minlength=len(SURFACE_CLASSES))
    assert (seen > 1000).all(), seen
    with pytest.raises(KeyError, match="unknown calibration surface"):
        make_surface("bowl")

