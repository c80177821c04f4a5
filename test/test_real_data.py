"""Issue 25 on the real profiler data: ``xmetro real-data`` calibrates through the documented ``xmetro calibrate``
path on the data set's training list and is scored on its validation list against what the data say (labels,
repeat means, repeat spreads); the data set's test split is not here and is never read. Also the profile
campaign's errors through ``xmetro calibrate``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import need_shared

from xmetro_ros.apps.cli import main as xmetro

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "measured"
R19 = DATA / "profiler_sphere_r19_labelled"
ATC5 = DATA / "atc5_profiler_sphere_r40"


@pytest.fixture(scope="module")
def summary(tmp_path_factory):
    need_shared(R19 / "train_file.txt", R19 / "val_file.txt", ATC5)
    out = tmp_path_factory.mktemp("real")
    # 500 iterations (the shipped figures use 1000): the acceptance must hold on the cheaper model too.
    assert xmetro(["real-data", "--out", str(out), "--iterations", "500"]) == 0
    s = json.loads((out / "summary.json").read_text())
    s["_out"] = str(out)
    return s


def test_segmentation_matches_the_labels(summary):
    seg = summary["segmentation"]["val"]
    assert seg["profiles"] == 348 and seg["no_arc"] == 0
    assert seg["median"] >= 0.90 and seg["below_0_5"] == 0


def test_d_beats_the_constant_and_the_incidence_baseline(summary):
    s = summary["systematic"]
    assert s["points"] > 100_000
    assert s["d_vs_constant"] <= 0.88, s
    assert s["d_vs_bin_baseline"] <= 0.95, s
    # The honest counterpart is reported, not hidden: at positions the training never saw, d gains much less.
    n = summary["new_position"]
    assert n["mae_d_um"] > s["mae_d_um"] and n["training_profiles"] < 1392


def test_u_covers_per_axis_and_per_incidence_bin(summary):
    c = summary["coverage_kept"]
    for ax in ("coverage_x", "coverage_z"):
        assert 0.93 <= c[ax] <= 0.97, c[ax]
    assert c["min_bin_coverage"] >= 0.90
    assert all(b["points"] > 0 for b in c["bins"])
    # U is mostly systematic error the model cannot explain, far wider than the repeats' random spread.
    r = summary["random_part"]
    assert r["U_median_um"] > 3 * r["repeat_spread_rms_um"]


def test_u_scores_the_points_the_labeller_called_border(summary):
    q = summary["quality"]
    assert q["positives_label0_on_sphere"] > 1000
    assert q["auc_U"] >= 0.75


def test_atc5_and_the_files_written(summary):
    a = summary["atc5"]
    assert a["with_arc"] == 15 and a["points_kept"] > 10_000
    # The poses agree with the arcs the segmentation found (the sphere's plane sections).
    assert a["arc_radius_minus_pose_mm"]["median_abs"] < 1.0
    assert a["in_r19_domain"] < 0.05  # another instrument's range: out of the r19 model's domain, and said so
    assert a["published_fraction"] == a["in_r19_domain"]  # and nothing is published there
    out = Path(summary["_out"])
    for f in ("campaign.yaml", "tables.md", "real_data_by_incidence.png", "cal/report.md",
              "cal/models/profile_catboost/model.onnx", "cal/models/profile_catboost/card.json"):
        assert (out / f).is_file(), f
    card = json.loads((out / "cal/models/profile_catboost/card.json").read_text())
    assert card["campaign"]["format"] == "xmetro-profile-campaign/1" and card["onnx_check"]["rows"] == 2000
    g = summary["geometry_sweep"]
    assert len(g["fan_origin"]) == 5 and len(g["camera"]) == 5
    # The scanner description the calibration could support, in the card: what was assumed, what was swept.
    geo = card["scanner"]["geometry"]
    assert "parallel" in geo["assumed"] and isinstance(geo["fan_origin"]["identified"], bool)
    assert geo["sweep"] == g


def _campaign(tmp_path, **over):
    names = [s for s in (R19 / "train_file.txt").read_text().split() if s][:48]
    lst = tmp_path / "list.txt"
    lst.write_text("\n".join(names) + "\n")
    doc = {"format": "xmetro-profile-campaign/1", "scanner": {"id": "p1"},
           "artifact": {"id": "s", "diameter_mm": 38.1}, "profiles": [{"list": "list.txt", "root": str(R19)}]}
    doc.update(over)
    f = tmp_path / "camp.yaml"
    f.write_text(yaml.safe_dump(doc))
    return f


def test_calibrate_cli_profile_campaign(tmp_path, capsys):
    need_shared(R19 / "train_file.txt")
    f = _campaign(tmp_path)
    assert xmetro(["calibrate", str(f), "--out", str(tmp_path / "o"), "--iterations", "30"]) == 0
    rep = json.loads((tmp_path / "o" / "report.json").read_text())
    assert rep["profiles"]["read"] == 48 and rep["segmentation_iou"]["median"] >= 0.9
    assert np.isfinite(rep["u_um_by_bin"][0])
    for bad, match in [({"artifact": None}, "artifact"), ({"profiles": [{"list": "nope.txt"}]}, "does not exist"),
                       ({"border_angle_deg": 95}, "border_angle_deg"), ({"scanner": {}}, "scanner.id")]:
        g = _campaign(tmp_path, **bad)
        assert xmetro(["calibrate", str(g), "--out", str(tmp_path / "bad")]) == 2
        assert match in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()
