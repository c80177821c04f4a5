"""`xmetro verify-recommend`: the recommendation followed in the virtual scanner, through the command line."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from xmetro_ros.apps import cli
from xmetro_ros.apps.verify_recommend import (
    HELD_OUT_REGIONS,
    REGIONS,
    SELECTION_REGIONS,
    VALIDATION_REGIONS,
    drawn_regions,
    region_centre,
    verify_regions,
)


def test_region_centres_lie_on_the_artifacts():
    for regions in (REGIONS, VALIDATION_REGIONS, SELECTION_REGIONS, drawn_regions(11000)):
        assert len(regions) >= 8 and {type(a).__name__ for a, _, _ in regions} == {"Sphere", "Cylinder"}
        for art, _, d in regions:
            c = region_centre(art, d)
            np.testing.assert_allclose(art.project(c[None])[0], c, atol=1e-9)
    # held-out: on the cylinder, region_centre reads x and z of a direction with a y part, so the last region's
    # centre lies 2.4 mm inside the surface (its 4 mm ball still holds surface points); kept as issue 29 was checked
    depth = [float(np.linalg.norm(a.project(region_centre(a, d)[None])[0] - region_centre(a, d)))
             for a, _, d in HELD_OUT_REGIONS]
    assert max(depth[:-1]) < 1e-3 and 2.0 < depth[-1] < 2.5
    # the validation regions (for choosing a model) are not the test regions, not even in place; the held-out ones
    # are other judged set-ups (a place recurs at other settings: the 45 mm sphere's top, validation and held-out)
    def places(regions):
        return {(a.to_dict().__repr__(), tuple(np.round(region_centre(a, d), 6))) for a, _, d in regions}

    def setups(regions):
        return {(a.to_dict().__repr__(), st, tuple(np.round(region_centre(a, d), 6))) for a, st, d in regions}

    assert not places(REGIONS) & places(VALIDATION_REGIONS)
    held = setups(HELD_OUT_REGIONS)
    assert len(held) == len(HELD_OUT_REGIONS) and not held & (setups(REGIONS) | setups(VALIDATION_REGIONS))
    # drawn sets (the selection set: seed 10000): the held-out kind, reproducible, and none of the sets above
    assert drawn_regions(10000) == SELECTION_REGIONS and len(SELECTION_REGIONS) == 12
    assert [st[2] for _, st, _ in SELECTION_REGIONS] == [0.5] * 9 + [0.1, 2.0, 0.1]
    for seed in (10000, 11000):
        drawn = places(drawn_regions(seed))
        assert len(drawn) == 12 and not drawn & (places(REGIONS) | places(VALIDATION_REGIONS)
                                                  | places(HELD_OUT_REGIONS))
        assert all(d[2] >= np.cos(np.radians(45)) - 1e-3 for _, _, d in drawn_regions(seed))


@pytest.fixture(scope="module")
def quick_report(tmp_path_factory):
    out = tmp_path_factory.mktemp("verify") / "v.json"
    assert cli.main(["verify-recommend", "--quick", "--regions", "1", "--radius", "3", "--effects",
                     "--out", str(out)]) == 0
    return json.loads(out.read_text())


def test_verify_recommend_cli(quick_report):
    rep = quick_report
    (r,) = rep["regions"]
    a = r["actual_p95_um"]
    # the actual best is measured on the same evaluation draws as the recommendation, which is among the finalists
    assert 0 < r["n_candidates"] <= 27 * 9
    assert a["best"] <= a["after"]
    assert np.linalg.norm(r["best_quaternion_xyzw"]) == pytest.approx(1.0, abs=1e-5)
    assert r["after_over_best"] == pytest.approx(a["after"] / a["best"])
    assert 0.0 <= r["after_percentile"] <= 1.0 and -1.0 <= r["rank_correlation"] <= 1.0
    # the shipped model predicts no uncertainty: the note says the ranking ignores noise
    assert "noise is ignored" in r["note"] or "|d| + |U|" in r["note"]
    assert 5.0 < a["before"] < 200.0 and r["coverage_after"] > 0.5
    assert rep["median"]["after_over_best"] == pytest.approx(r["after_over_best"])
    # the search: the shipped ensemble, each member with the calibration in its own card, said in the note
    cals = rep["recommender_calibration"]
    assert len(cals) == 3 and all(c["source"] == "the model card's" and c["prediction_rel_unc"] > 0 for c in cals)
    assert rep["model"] == "ensemble:" + "+".join(c["model"] for c in cals)
    assert "search ensemble of 3 pose models" in r["note"] and "recommender calibration: the model card's" in r["note"]
    # --effects: before's and after's systematic p95 with each effect switched off, next to the predicted one
    for k in ("before", "after"):
        e = r["systematic_p95_um"][k]
        assert e["predicted"] > 0 and {"all", "standoff", "centroid", "motion_blur"} <= set(e["actual_without"])
        assert all(np.isfinite(v) and v >= 0 for v in e["actual_without"].values())
        # speckle is random only: the systematic part without it is the same but for the few points its noise moves
        # into or out of the region (the p95 is taken over the re-simulated points in it); the stand-off bias is
        # systematic
        assert e["actual_without"]["speckle"] == pytest.approx(e["actual_without"]["all"], rel=3e-4)
        assert e["actual_without"]["standoff"] != pytest.approx(e["actual_without"]["all"], rel=1e-3)


def test_verify_recommend_refuses_a_pose_model_that_does_not_match(tmp_path, capsys):
    """A --pose-model for other features or another scanner than the judging model: exit 2 and why, no report
    (the node's rule: inference.load_pose_model)."""
    import shutil

    from xmetro_ros.scan.resources import pose_model_dir

    for key, change in (("feature_names", lambda v: list(reversed(v))), ("scanner", lambda v: {"id": "ls-200"})):
        odd = tmp_path / key
        shutil.copytree(pose_model_dir(), odd)
        card = json.loads((odd / "card.json").read_text())
        card[key] = change(card.get(key))
        if key == "feature_names":
            card["feature_units"] = list(reversed(card["feature_units"]))
        (odd / "card.json").write_text(json.dumps(card))
        out = tmp_path / f"{key}.json"
        assert cli.main(["verify-recommend", "--quick", "--regions", "1", "--pose-model", str(odd),
                         "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert ("not the primary model's" if key == "feature_names" else "trained for scanner 'ls-200'") in err
        assert not out.exists()


def test_verify_recommend_against_all_candidates(tmp_path, quick_report):
    """--against-all keeps the search's recommendation and seeks the actual best among every candidate, those the
    domain check discards included (more candidates, the same "after", a best at least as good)."""
    out = tmp_path / "all.json"
    assert cli.main(["verify-recommend", "--quick", "--regions", "1", "--radius", "3", "--against-all",
                     "--out", str(out)]) == 0
    rep = json.loads(out.read_text())
    (r,), (q,) = rep["regions"], quick_report["regions"]
    assert rep["candidates_checked"].startswith("all") and quick_report["candidates_checked"] == "the search's"
    assert r["recommended_settings"] == q["recommended_settings"]
    assert r["actual_p95_um"]["after"] == q["actual_p95_um"]["after"]
    assert r["n_candidates"] >= q["n_candidates"] and r["actual_p95_um"]["best"] <= r["actual_p95_um"]["after"]


def test_shipped_model_recommendations_hold_when_followed():
    """Issue 15's acceptance on the shipped model sets as the node runs them (scans judged by the primary or the pose
    model, the search with the shipped search ensemble), re-simulated over the nine test regions (seeds 7000-7008,
    never used in training or in choosing a model, which the validation regions did): following the recommendation
    never makes the actual p95 worse beyond the re-simulation noise; after / best actual ≤ 1.25 in every region,
    median ≤ 1.1; the predicted p95 after within ±30 % of the actual; rank correlation of predicted and actual p95
    over the candidates ≥ 0.7 (median)."""
    rep = verify_regions(None)
    assert rep["model"].startswith("ensemble:") and len(rep["judge_models"]) == 2
    R = rep["regions"]
    assert len(R) == 9
    for r in R:
        a = r["actual_p95_um"]
        assert a["after"] <= a["before"] + 3 * max(a["after_spread"], 0.1), r
        assert abs(r["predicted_p95_um"]["after"] / a["after"] - 1) <= 0.3, r
    ratios = np.array([r["after_over_best"] for r in R])
    print("after / best:", np.round(ratios, 3), "rank correlation:", [round(r["rank_correlation"], 2) for r in R])
    assert ratios.max() <= 1.25 and np.median(ratios) <= 1.1, ratios
    assert np.median([r["rank_correlation"] for r in R]) >= 0.7


def test_calibrate_the_recommender_on_validation_regions(tmp_path, capsys):
    """``--calibrate`` (here on one validation region, tilts only): the factor on U per exposure is the median
    re-simulated random-part p95 over the predicted p95 |U|, relative to 0.5 ms; the relative uncertainty is the
    sign-flipped 5 % quantile of the gain errors of the 20 best-ranked candidates (0 when that is a gain
    under-predicted). ``--write-card`` puts both into the searched model set's card, where the search finds them;
    a directory holding another model set is refused before the work."""
    from xmetro_ros.judge.inference import ModelSet
    from xmetro_ros.plan.recommend import recommend_calibration
    from xmetro_ros.scan.resources import default_model_dir, pose_model_dir

    own, other = tmp_path / "own", tmp_path / "other"
    shutil.copytree(pose_model_dir(), own)
    shutil.copytree(default_model_dir(), other)
    before = (other / "card.json").read_text()
    assert cli.main(["verify-recommend", "--calibrate", "--quick", "--regions", "1", "--pose-model", str(own),
                     "--write-card", str(other)]) == 2
    assert "is model set" in capsys.readouterr().err and (other / "card.json").read_text() == before
    assert recommend_calibration(ModelSet.load(own)).source == "the shipped pose model's"
    out = tmp_path / "c.json"
    assert cli.main(["verify-recommend", "--calibrate", "--quick", "--regions", "1", "--pose-model", str(own),
                     "--write-card", str(own), "--out", str(out)]) == 0
    rep = json.loads(out.read_text())
    cal = recommend_calibration(ModelSet.load(own))
    assert cal.source == "the model card's" and cal.prediction_rel_unc == rep["prediction_rel_unc"] >= 0.0
    assert cal.exposure_u_scale == {float(e): v for e, v in rep["exposure_u_scale"].items()}
    med, table = rep["random_over_u_p95_median"], rep["exposure_u_scale"]
    assert rep["region_set"] == "validation" and set(table) == {"0.1", "0.5", "2.0"} and table["0.5"] == 1.0
    for e, v in table.items():
        assert v == pytest.approx(med[e] / med["0.5"], abs=0.006) and rep["n_per_exposure"][e] > 0
    # the simulator's random part is of the order of U: a ratio far from 1 would be a broken U
    assert all(0.3 < v < 3.0 for v in med.values())
    g = rep["gain_error_rel"]
    assert g["n"] == 20 and g["quantile"] == 0.05 and 0.0 < g["sd"] < 1.0
    assert g["mean"] - 3 * g["sd"] <= -rep["prediction_rel_unc"] <= max(g["mean"], 0.0)  # a low quantile, clipped
