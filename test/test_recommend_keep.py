"""Issue 29 (part 1): "keep the current set-up" is a candidate like any other; the random part at each candidate's
exposure enters the ranking with its calibrated size; no followed recommendation makes a region worse."""

from __future__ import annotations

import numpy as np
import pytest

from xmetro_ros.judge.features import FeatureContext, compute_features
from xmetro_ros.plan.recommend import (
    EXPOSURE_U_SCALE,
    PREDICTION_REL_UNC,
    RecommendCalibration,
    gain_and_uncertainty,
    recommend,
    recommend_calibration,
    u_scale,
)
from xmetro_ros.scan.artifacts import Sphere
from xmetro_ros.scan.geometry import point_geometry
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings
from xmetro_ros.sim import simulate_scan


def test_u_scale_interpolates_in_log_exposure():
    t = {0.1: 2.0, 0.5: 1.0, 2.0: 1.5}
    assert u_scale(0.5, t) == 1.0 and u_scale(0.1, t) == 2.0 and u_scale(2.0, t) == 1.5
    assert u_scale(1.0, t) == pytest.approx(1.25)  # log(1) halfway between log(0.5) and log(2)
    assert u_scale(0.05, t) == 2.0 and u_scale(5.0, t) == 1.5  # clipped at the ends
    assert u_scale(3.0, None) == 1.0 and u_scale(3.0, {}) == 1.0
    assert EXPOSURE_U_SCALE[0.5] == 1.0


class Tilted:
    """A small systematic error growing with tilt (1 − Inc) and a U given per call."""

    feature_names = ("exposure_time", "Inc")

    def __init__(self, u):
        self.u = u

    def predict(self, X):
        X = np.asarray(X, np.float64)
        return np.stack([np.zeros(len(X)), np.zeros(len(X)), 0.001 + 0.01 * (1 - X[:, 1])], axis=1)

    def predict_batch(self, Xq):
        return np.stack([self.predict(x) for x in Xq])

    def predict_with_uncertainty(self, X):
        return self.predict(X), self.u(np.asarray(X))


def _context(scan, scanner) -> FeatureContext:
    """Feature context of a simulated scan's points with the true normals (no preprocessing)."""
    pts = scan.points.reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    g = point_geometry(pts, scan.pose, scanner.baseline_mm)
    return FeatureContext(normals=scan.artifact.normals(scan.artifact.project(pts)), L=g.L, V=g.V,
                          standoff=g.standoff, source_distance=g.source_distance, settings=scan.settings, points=pts,
                          u=g.u, s=g.s, camera_mm=scanner.camera_mm)


def test_random_part_scaled_per_exposure_and_keep_rule():
    """The factor on U at each exposure multiplies the candidates' p95 |U| (and so enters score and predicted p95);
    a predicted gain inside the uncertainty of the predictions keeps the current set-up, with the reason in the
    note; without the model's relative error the same gain is taken."""
    scanner = ScannerModel.load()
    judged = simulate_scan(Sphere(22.5), ScanSettings(6.0, 3.0, 0.5), scanner=scanner, seed=6)
    ctx = _context(judged, scanner)
    c0 = np.array([9.0, 0.0, np.sqrt(22.5**2 - 81)])  # a sloped patch: tilting towards it lowers the error
    rows = np.flatnonzero(np.linalg.norm(np.asarray(ctx.points) - c0, axis=1) < 4)
    m = Tilted(lambda X: np.full((len(X), 3), 0.004))  # U the same at every exposure
    feats = compute_features(list(m.feature_names), ctx)
    kw = dict(max_points=300, tilt_steps=3, turn_steps=1, in_domain=False)
    args = (m, ctx, rows, feats, judged.pose, scanner, judged.settings)
    raw = recommend(*args, **kw, exposure_u_scale=None, keep_current=False)
    scaled = recommend(*args, **kw, exposure_u_scale={0.5: 1.0, 2.0: 3.0}, keep_current=False)
    by = {(c.settings, c.rotation.tobytes()): c for c in raw.ranked}
    for c in scaled.ranked:
        r = by[(c.settings, c.rotation.tobytes())]
        f = u_scale(c.settings.exposure_ms, {0.5: 1.0, 2.0: 3.0})
        assert c.u_p95_mm == pytest.approx(f * r.u_p95_mm, rel=1e-5)
        assert c.p95_mm == pytest.approx(r.p95_mm, rel=1e-9)  # the systematic part is not touched
    # the 2 ms candidates, the same as 0.5 ms ones without the factor, fall behind with it
    assert scaled.top.settings.exposure_ms < 2.0
    assert "calibrated size" in scaled.note and "calibrated size" not in raw.note
    # keep rule: the model's relative error decides between "change" and "keep"
    change = recommend(*args, **kw, prediction_rel_unc=0.0)
    gain, unc0 = gain_and_uncertainty(change.before, change.top, 0.0)
    assert gain > unc0 and not change.kept_current and change.best is change.top
    rel = 1.5 * gain / np.hypot(change.before.reported_p95_mm, change.top.reported_p95_mm)
    keep = recommend(*args, **kw, prediction_rel_unc=rel)
    assert keep.kept_current and "keep the current set-up" in keep.note
    assert keep.best.settings == judged.settings and np.allclose(keep.best.rotation, np.eye(3))
    assert keep.top.settings == change.top.settings  # the best-ranked candidate is still reported
    g, u = gain_and_uncertainty(keep.before, keep.top, rel)
    assert g == pytest.approx(gain) and u > g and f"{u * 1e3:.1f} um" in keep.note


def test_the_searched_model_sets_own_calibration():
    """A model card's ``recommend`` block (``xmetro verify-recommend --calibrate --write-card``) replaces the shipped
    pose model's factors on U and relative uncertainty in the search, says so in the note; a malformed one is
    refused; explicit arguments still win."""
    scanner = ScannerModel.load()
    judged = simulate_scan(Sphere(22.5), ScanSettings(6.0, 3.0, 0.5), scanner=scanner, seed=6)
    ctx = _context(judged, scanner)
    c0 = np.array([9.0, 0.0, np.sqrt(22.5**2 - 81)])
    rows = np.flatnonzero(np.linalg.norm(np.asarray(ctx.points) - c0, axis=1) < 4)
    m = Tilted(lambda X: np.full((len(X), 3), 0.004))
    feats = compute_features(list(m.feature_names), ctx)
    kw = dict(max_points=300, tilt_steps=3, turn_steps=1, in_domain=False)
    args = (m, ctx, rows, feats, judged.pose, scanner, judged.settings)
    assert recommend_calibration(m) == RecommendCalibration(EXPOSURE_U_SCALE, PREDICTION_REL_UNC,
                                                            "the shipped pose model's")
    shipped = recommend(*args, **kw)
    assert "recommender calibration: the shipped pose model's" in shipped.note
    explicit = recommend(*args, **kw, exposure_u_scale=EXPOSURE_U_SCALE, prediction_rel_unc=PREDICTION_REL_UNC)
    assert [c.score_mm for c in shipped.ranked] == [c.score_mm for c in explicit.ranked]
    assert "recommender calibration" not in explicit.note
    change = recommend(*args, **kw, exposure_u_scale={0.5: 1.0, 2.0: 3.0}, prediction_rel_unc=0.0)
    gain, _ = gain_and_uncertainty(change.before, change.top, 0.0)
    rel = 1.5 * gain / np.hypot(change.before.reported_p95_mm, change.top.reported_p95_mm)
    # JSON keys are strings: the card's exposures are read as numbers
    m.card = {"recommend": {"exposure_u_scale": {"0.5": 1.0, "2.0": 3.0}, "prediction_rel_unc": rel}}
    own = recommend(*args, **kw)
    assert own.kept_current and "keep the current set-up" in own.note
    assert "recommender calibration: the model card's" in own.note
    by = {(c.settings, c.rotation.tobytes()): c for c in change.ranked}
    assert all(c.u_p95_mm == pytest.approx(by[(c.settings, c.rotation.tobytes())].u_p95_mm) for c in own.ranked)
    assert not recommend(*args, **kw, prediction_rel_unc=0.0).kept_current  # an explicit figure wins
    for bad in ({"prediction_rel_unc": 0.1}, {"exposure_u_scale": {"0.5": 1.0}, "prediction_rel_unc": -0.1},
                {"exposure_u_scale": {"0.5": "x"}, "prediction_rel_unc": 0.1}):
        m.card = {"recommend": bad}
        with pytest.raises(ValueError, match="'recommend' block"):
            recommend(*args, **kw)


def test_no_followed_recommendation_makes_a_region_worse():
    """Issue 29's acceptance on the shipped model sets as the node runs them (``plan.resim.verify`` exactly as
    ``xmetro verify-recommend``: the primary or the pose model judges by routing, the shipped search ensemble
    searches), over the held-out regions (``verify_recommend.HELD_OUT_REGIONS``): no region worse than staying
    beyond the re-simulation's own spread (hypot of the before and after p95 spreads over the 3 evaluation seeds),
    median after / best ≤ 1.1; the issue's case (region 1: a 45 mm sphere at 10/4/0.5, a predicted gain inside its
    uncertainty) and region 2 (the single pose model's miss: a 35 mm sphere at 6/5/0.5, told to turn) keep the
    current set-up."""
    from xmetro_ros.apps.verify_recommend import HELD_OUT_REGIONS, verify_regions

    rep = verify_regions(None, region_set="held-out")
    R = rep["regions"]
    assert len(R) == len(HELD_OUT_REGIONS) and rep["region_set"] == "held-out"
    for k, r in enumerate(R):
        a, p, g = r["actual_p95_um"], r["predicted_p95_um"], r["predicted_gain_um"]
        print(f"region {k} {r['judged_settings']}: {'kept' if r['kept_current'] else 'changed'} "
              f"-> {r['recommended_settings']}; predicted {p['before']:.2f} -> {p['after']:.2f} um "
              f"(gain {g['gain']:.2f} ± {g['uncertainty']:.2f}); actual {a['before']:.2f} ± {a['before_spread']:.2f}"
              f" -> {a['after']:.2f} ± {a['after_spread']:.2f} um, best {a['best']:.2f}, "
              f"after/best {r['after_over_best']:.3f}")
    for r in R:
        a = r["actual_p95_um"]
        assert a["after"] - a["before"] <= max(np.hypot(a["before_spread"], a["after_spread"]), 0.1), r
        if r["kept_current"]:
            assert a["after"] == a["before"] and "keep the current set-up" in r["note"]
        else:
            assert r["predicted_gain_um"]["gain"] > r["predicted_gain_um"]["uncertainty"]
    ratios = np.array([r["after_over_best"] for r in R])
    assert np.median(ratios) <= 1.1, ratios
    assert R[1]["kept_current"] and R[2]["kept_current"]
    assert rep["model"].startswith("ensemble:")


class Sloped(Tilted):
    """``Tilted`` with its growth with tilt scaled by ``slope`` (0: the same error at every orientation)."""

    def __init__(self, u, slope: float, name: str):
        super().__init__(u)
        self.slope, self.id = slope, name

    def predict(self, X):
        d = super().predict(X)
        d[:, 2] = 0.001 + self.slope * (d[:, 2] - 0.001)
        return d


def test_search_ensemble_ranks_on_the_mean_and_keeps_on_disagreement():
    """Members that agree give the single model's answer; members that disagree on the gain keep the current
    set-up where one of them alone would have advised a change (``plan.ensemble_search``)."""
    from xmetro_ros.plan.ensemble_search import SearchEnsemble, ensemble_gain, search

    scanner = ScannerModel.load()
    judged = simulate_scan(Sphere(22.5), ScanSettings(6.0, 3.0, 0.5), scanner=scanner, seed=6)
    ctx = _context(judged, scanner)
    c0 = np.array([9.0, 0.0, np.sqrt(22.5**2 - 81)])
    rows = np.flatnonzero(np.linalg.norm(np.asarray(ctx.points) - c0, axis=1) < 4)
    u = lambda X: np.full((len(X), 3), 0.002)  # noqa: E731
    a, a2, flat = Sloped(u, 1.0, "a"), Sloped(u, 1.0, "a2"), Sloped(u, 0.0, "flat")
    feats = compute_features(list(a.feature_names), ctx)
    kw = dict(max_points=300, tilt_steps=3, turn_steps=1, in_domain=False, prediction_rel_unc=0.0)
    rest = (ctx, rows, feats, judged.pose, scanner, judged.settings)
    single = recommend(a, *rest, **kw)
    agree = search(SearchEnsemble([a, a2]), *rest, **kw)
    assert search(a, *rest, **kw).gain == single.gain  # one model set: recommend itself
    assert not single.kept_current and not agree.kept_current
    assert [c.settings for c in agree.ranked] == [c.settings for c in single.ranked]
    assert [c.score_mm for c in agree.ranked] == pytest.approx([c.score_mm for c in single.ranked], rel=1e-9)
    assert agree.gain == pytest.approx(single.gain, rel=1e-9) and agree.best.settings == single.best.settings
    assert "search ensemble of 2 pose models (a, a2)" in agree.note
    # one member sees the gain, the other none: their spread keeps the current set-up
    split = search(SearchEnsemble([a, flat]), *rest, **kw)
    g_a = single.before.reported_p95_mm - single.top.reported_p95_mm
    assert split.kept_current and "keep the current set-up" in split.note and "theirs and their spread" in split.note
    assert split.best.settings == judged.settings and np.allclose(split.best.rotation, np.eye(3))
    gain, unc = split.gain
    assert 0 < gain < g_a and unc > gain
    # the rule itself: mean gain against the members' own uncertainties and their spread (M - 1)
    assert ensemble_gain(np.array([5.0, 5.0, 5.0]), np.array([1.0, 1.0, 1.0])) == pytest.approx((5.0, 1.0))
    g, s = ensemble_gain(np.array([4.75, 1.82, 0.3]), np.array([1.1, 3.5, 5.3]))
    assert g == pytest.approx(2.29) and s == pytest.approx(np.sqrt((1.1**2 + 3.5**2 + 5.3**2) / 3 + 5.1163), rel=1e-3)
    assert s > g  # issue 29's held-out miss, one member's confident gain: kept
    assert ensemble_gain(np.array([np.inf, 3.0]), np.array([1.0, 1.0]))[0] == np.inf
    with pytest.raises(ValueError, match="at least 2"):
        SearchEnsemble([a])


def test_shipped_search_ensemble_loads():
    """The shipped search ensemble: three pose model sets taking the primary's features, each with its own
    recommender calibration; a directory without one is refused."""
    from xmetro_ros.judge.inference import ModelSet
    from xmetro_ros.plan.ensemble_search import load_search_ensemble
    from xmetro_ros.scan.resources import search_models_dir, search_models_path

    primary = ModelSet.load(None)
    ens = load_search_ensemble(search_models_dir(), primary)
    assert len(ens.members) == 3 and len({m.id for m in ens.members}) == 3
    assert all(recommend_calibration(m).source != "the shipped pose model's" for m in ens.members)
    assert ens.id.startswith("ensemble:") and ens.feature_names == list(primary.feature_names)
    assert search_models_path(None, None, None) == search_models_dir()
    assert search_models_path("mine", None, None) is None and search_models_path(None, "mine", "") is None
    assert search_models_path(None, None, "none") is None
    with pytest.raises(ValueError, match="at least 2"):
        load_search_ensemble(search_models_dir() / "s2", primary)
