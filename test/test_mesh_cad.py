"""Judging a mesh part against its CAD (issue 18): the compensation lowers the deviation error, the intervals hold
where the judge calls the points in domain, `xmetro predict --cad` reports the same maps offline."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("open3d")

from xmetro_ros.judge.inference import ModelSet
from xmetro_ros.judge.scan_handler import ScanHandler
from xmetro_ros.parts.study import PRESENTATION, evaluate_part
from xmetro_ros.scan.generated_parts import make_part
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings
from xmetro_ros.sim import simulate_scan


@pytest.fixture(scope="module")
def handler() -> ScanHandler:
    return ScanHandler(ModelSet.load(), ScannerModel.load())


@pytest.mark.parametrize("part", ["blade", "bowl", "step", "fillet"])
def test_compensation_lowers_the_deviation_error_against_cad(handler: ScanHandler, part: str) -> None:
    """Each part (never trained on), the study's low densities at the default exposure, pose known: MAE and p95 of
    |measured − CAD − true form error| drop with the model's compensation (measured factors 1.29-1.84 and
    1.24-1.62); the intervals cover ≥ 90 % of the in-domain points, overall and per region type (types with ≥ 100
    in-domain points), and the points the shape domain flags are where they fail most."""
    r = evaluate_part(part, handler, ScanSettings(6.0, 3.0, 0.5), seed=7, register=False)
    # a scan the compensation improves is not sent back (issue 28 saw RESCAN or WARN on parts like these)
    assert r["verdict"] == "OK", r["verdict_message"]
    kp = r["cad"]["known_pose"]
    assert kp["after"]["mae_um"] < kp["before"]["mae_um"] / 1.2
    assert kp["after"]["p95_um"] < kp["before"]["p95_um"] / 1.15
    cov = r["coverage"]
    assert cov["in_domain"]["n"] > 2000 and cov["in_domain"]["coverage"] >= 0.90  # bowl: 2.8k of 32k
    for name, g in cov["regions"].items():
        if g["in_domain"]["n"] >= 100:
            assert g["in_domain"]["coverage"] >= 0.90, (name, g)
    assert r["mae_ratio_to_oracle"][2] < 1.1  # Z, the largest error, near the floor
    # Along the CAD normal per region type: the regions partition the points, and each share is the coverage of
    # |after − true form| ≤ u_normal on that region's points (the overall figure is their weighted mean).
    nreg = kp["normal_coverage_regions"]
    assert sum(g["n"] for g in nreg.values()) == r["points"]
    assert sum(g["n"] * g["all"] for g in nreg.values() if g["n"]) == pytest.approx(kp["normal_coverage"]
                                                                                    * r["points"])
    # The shape part of the domain (curvature outside the calibration's spheres and cylinder) says where the
    # intervals fail: its points are covered less and hold a larger share of the misses than of the points.
    assert cov["shape_in_domain"]["coverage"] >= 0.90
    so = cov["shape_out_of_domain"]
    if so["n"] >= 100:
        assert so["coverage"] < cov["shape_in_domain"]["coverage"], (so, cov["shape_in_domain"])
        assert r["misses_shape_out_of_domain_share"] > r["shape_out_of_domain_share"]


def test_predict_cad_offline(tmp_path, handler: ScanHandler) -> None:
    """`xmetro predict BAG --out OUT --cad PART.stl --cad-pose ...`: the report's maps are those of cad_deviation on
    the same judged scan (through the node's core and its ~/deviations cloud, float32 metres)."""
    from xmetro_ros.apps.cli import main
    from xmetro_ros.parts.cad_judge import cad_deviation
    from xmetro_ros.ros.scan_io import write_scans
    from xmetro_ros.scan.mesh import write_stl
    from xmetro_ros.scan.part_pose import format_pose7

    cad = make_part("step")
    stl = write_stl(tmp_path / "step.stl", cad.vertices, cad.triangles)
    scan = simulate_scan(make_part("step", form_um=40.0).transformed(PRESENTATION), ScanSettings(4.0, 2.0, 0.5),
                         seed=2)
    bag = write_scans(tmp_path / "in.mcap", [scan])
    pose = format_pose7(PRESENTATION)  # x y z (m) qx qy qz qw, as the node's cad_pose
    rc = main(["predict", str(bag), "--out", str(tmp_path / "out.mcap"), "--cad", str(stl), "--cad-pose", pose])
    assert rc == 0
    rep = json.loads((tmp_path / "out.cad.json").read_text())
    row = rep["scans"][0]
    res = handler.process(scan)
    pts = np.asarray(res.scan.points).reshape(-1, 3)
    direct = cad_deviation(cad, pts, res.deviations, res.uncertainty, pose=PRESENTATION).summary()
    assert row["points"] == direct["points"] > 1000
    for k in ("before", "after", "u_normal"):
        assert row[k]["mean_abs"] == pytest.approx(direct[k]["mean_abs"], rel=1e-3, abs=0.01)
    assert np.isfinite(row["u_normal"]["mean"]) and row["u_normal"]["mean"] > 0


@pytest.mark.parametrize("part", ["blade", "bowl"])
def test_intervals_hold_per_axis_at_short_exposure(handler: ScanHandler, part: str) -> None:
    """Issue 28's failures, with other draws than the study's: at 6/3/0.1 the bowl's z (its flat top: σ̂ 13 µm for a
    true 16 µm) and the twisted blade's y (σ̂ too flat in |N_y|) were covered 84-89 %. With the scan's measured
    noise under σ̂ (preprocess/noise.py, judge/measured_noise.py) every axis covers ≥ 93 % of the in-domain points
    against the simulator's truth (the study's draws: 94.0-98.4 %)."""
    r = evaluate_part(part, handler, ScanSettings(6.0, 3.0, 0.1), seed=11, register=False)
    cov = r["coverage"]["in_domain"]
    assert cov["n"] > 10_000
    assert min(cov["coverage_xyz"]) >= 0.93, cov["coverage_xyz"]


@pytest.fixture(scope="module")
def handler_with_pose_model() -> ScanHandler:
    from xmetro_ros.scan.resources import pose_model_dir

    return ScanHandler(ModelSet.load(), ScannerModel.load(), pose_model=ModelSet.load(pose_model_dir()))


@pytest.mark.parametrize("part", ["blade", "bowl", "step"])
@pytest.mark.parametrize("grid_index", [5, 19])
def test_intervals_hold_on_parts_rescanned_from_tilted_heads(handler_with_pose_model: ScanHandler, part: str,
                                                             grid_index: int) -> None:
    """A rescan from one of the recommender's tilted head poses (15°) goes to the pose model: its U must hold on a
    part as the primary's does looking down. Before the pose model's card had the per-class multipliers on the
    measured noise (0.8.1, ``xmetro export-default --add-surfaces``) the blade's y covered 76-89 % and the bowl's and
    the step's z 88-91 % at 6/3/0.1 (other poses and draws than these)."""
    from xmetro_ros.sim.campaign import pose_grid

    h = handler_with_pose_model
    rot = pose_grid()[grid_index]
    assert np.degrees(np.arccos(np.clip(rot[2, 2], -1, 1))) == pytest.approx(15.0, abs=0.1)
    r = evaluate_part(part, h, ScanSettings(6.0, 3.0, 0.1), seed=33, register=False, head_rotation=rot)
    assert r["judged_by"] == h.pose_model.id
    cov = r["coverage"]["in_domain"]
    assert cov["n"] > 5_000
    assert min(cov["coverage_xyz"]) >= 0.93, cov["coverage_xyz"]
    assert r["cad"]["known_pose"]["normal_coverage_in_domain"] >= 0.93  # along the CAD normal, as parts.md quotes


#: Issue 28's parts beyond blade, bowl and step (fillet is ours): none is in a training or calibration campaign (the
#: calibration saddle is symmetric, ±1/30 /mm; this one is +1/25 and −1/45).
NEW_PARTS = ("saddle", "torus", "eggcrate")


@pytest.fixture(scope="module")
def new_parts_at_default(handler: ScanHandler) -> dict[str, dict]:
    """The three parts at issue 28's default setting 10/4/0.5, other draws than the study's (seed 17)."""
    return {p: evaluate_part(p, handler, ScanSettings(10.0, 4.0, 0.5), seed=17, register=False) for p in NEW_PARTS}


@pytest.mark.parametrize("part", NEW_PARTS)
def test_issue_28_acceptance_met_on_the_new_parts(new_parts_at_default: dict[str, dict], part: str) -> None:
    """What issue 28 asks and these parts meet at 10/4/0.5 (measured, seed 17): compensation MAE after / before
    ≤ 0.8 (0.67-0.70), at most 30 % of the points out of domain (0.1-13.3 %), along the CAD normal and on Z
    (the error's largest axis) a coverage in [93, 97] % (95.5-96.5 %), Z at the oracle floor, verdict OK."""
    r = new_parts_at_default[part]
    assert r["verdict"] == "OK", r["verdict_message"]
    kp = r["cad"]["known_pose"]
    assert kp["after"]["mae_um"] <= 0.8 * kp["before"]["mae_um"]
    assert r["out_of_domain_share"] <= 0.30
    assert 0.93 <= kp["normal_coverage_in_domain"] <= 0.97
    assert 0.93 <= r["coverage"]["in_domain"]["coverage_xyz"][2] <= 0.97
    assert r["mae_ratio_to_oracle"][2] < 1.1


@pytest.mark.parametrize("part", [
    pytest.param("saddle", marks=pytest.mark.xfail(strict=True, reason=(
        "issue 28 open: the saddle's X covers 89.8 % (90.3 % in the study): where it rises towards +x the model "
        "predicts X −0.7 to −0.4 µm for a systematic +1.3 to +2.6 µm (tools/saddle_bias.py), unflagged"))),
    pytest.param("torus", marks=pytest.mark.xfail(strict=True, reason=(
        "issue 28 open: X / Y cover 97.2 / 97.8 %, above 97 %: on the torus's flat plate the X / Y error is ~0 "
        "and U does not go below its 1 µm floor times the class multiplier"))),
    "eggcrate"])
def test_issue_28_every_axis_within_93_97(new_parts_at_default: dict[str, dict], part: str) -> None:
    """Issue 28's per-axis bounds: the in-domain coverage of each axis in [93, 97] %. Met on the egg-crate (93.8 /
    96.7 / 96.1 %); the saddle and the torus fail it (strict xfail: a fix turns them into failures to remove)."""
    xyz = new_parts_at_default[part]["coverage"]["in_domain"]["coverage_xyz"]
    assert all(0.93 <= c <= 0.97 for c in xyz), xyz


@pytest.mark.parametrize("part", [
    "saddle", "torus",
    pytest.param("eggcrate", marks=pytest.mark.xfail(strict=True, reason=(
        "issue 28 open: the shape domain flags the egg-crate's bumps and pits (κ ≈ ±0.15 /mm both ways, a shape "
        "no calibration surface has) where the intervals hold: 13.3 % of the points, 10.0 % of the misses")))])
def test_issue_28_flagged_points_hold_their_share_of_the_misses(new_parts_at_default: dict[str, dict],
                                                                 part: str) -> None:
    """The points flagged out of domain hold at least their share of the misses (point, axis pairs outside U)."""
    r = new_parts_at_default[part]
    assert r["misses_out_of_domain_share"] >= r["out_of_domain_share"], (r["misses_out_of_domain_share"],
                                                                          r["out_of_domain_share"])
