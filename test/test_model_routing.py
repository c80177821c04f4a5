"""Two model sets (ROS-free): the primary judges the scans its domain holds; a scan taken at one of the rescan
recommender's orientations, outside the primary's domain and inside the shipped pose model's, is judged by the pose
model, exactly as that model alone would judge it; a pose outside both, or a part scanned looking down, stays with
the primary; the node's core loads the pose model only next to the shipped primary, with the same features and
scanner."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from xmetro_ros.judge import flags as fl
from xmetro_ros.judge.inference import ModelSet
from xmetro_ros.judge.scan_handler import ROUTE_MAX_OUT_OF_DOMAIN, HandlerParams, ScanHandler
from xmetro_ros.plan.recommend import RecommendCalibration, recommend_calibration
from xmetro_ros.scan.artifacts import Sphere
from xmetro_ros.scan.geometry import HeadPose, rotation_xyz
from xmetro_ros.scan.resources import default_model_dir, pose_model_dir
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings
from xmetro_ros.sim import simulate_scan


@pytest.fixture(scope="module")
def models():
    return ModelSet.load(default_model_dir()), ModelSet.load(pose_model_dir())


def _scan(r_head, seed=3):
    pose = None if r_head is None else HeadPose.looking_down(90.0).rotated(r_head, pivot=np.array([0, 0, 22.5]))
    return simulate_scan(Sphere(22.5), ScanSettings(10.0, 4.0, 0.5), seed=seed, pose=pose)


def _ood(res) -> float:
    f = res.flags[np.isfinite(res.deviations[:, 0])]
    return float(((f & fl.FLAG_OUT_OF_DOMAIN) > 0).mean())


def test_shipped_pose_model_is_the_pose_campaigns(models):
    primary, pose = models
    assert primary.id != pose.id and list(primary.feature_names) == list(pose.feature_names)
    assert pose.card["profile"] == "default" and pose.calibrated
    assert "--profile default" in pose.card["trained_by"]
    assert pose.card["data_manifest"]["campaign_args"]["pose_mode"] == "cycle"


@pytest.mark.parametrize("name, r_head, routed", [
    ("looking down", None, "primary"),
    ("tilt 15 deg", rotation_xyz(0.2618, 0.0, 0.0), "pose"),
    ("turn 90 deg", rotation_xyz(0.0, 0.0, 1.5708), "pose"),
    ("tilt 15 + turn 90", rotation_xyz(0.2618, 0.2618, 1.5708), "pose"),
    ("tilt 40 deg: outside both", rotation_xyz(0.698, 0.0, 0.0), "primary"),
])
def test_each_scan_is_judged_by_the_model_whose_domain_holds_it(models, name, r_head, routed):
    primary, pose = models
    scanner = ScannerModel.load()
    scan = _scan(r_head)
    both = ScanHandler(primary, scanner, HandlerParams(), pose_model=pose).process(scan)
    alone = {m.id: ScanHandler(m, scanner, HandlerParams()).process(scan) for m in (primary, pose)}
    want = (primary if routed == "primary" else pose).id
    assert both.model_id == both.quality["model_id"] == want, name
    # the routed judgement is that model's own, bit for bit
    ref = alone[want]
    np.testing.assert_array_equal(both.deviations, ref.deviations)
    np.testing.assert_array_equal(both.uncertainty, ref.uncertainty)
    np.testing.assert_array_equal(both.flags, ref.flags)
    if routed == "pose":  # why: the primary's domain does not hold the scan, the pose model's does
        assert _ood(alone[primary.id]) > ROUTE_MAX_OUT_OF_DOMAIN and _ood(alone[pose.id]) < ROUTE_MAX_OUT_OF_DOMAIN
    # without a second model every scan is the primary's
    assert ScanHandler(primary, scanner, HandlerParams()).process(scan).model_id == primary.id


def test_a_looking_down_part_stays_with_the_primary(models):
    """A part scanned looking down (the step, presented as in the parts study) stays with the primary, whose figures
    on the parts are the documented ones (docs/parts-generalisation.md): its head orientation is the primary's, and
    since the primary's card is calibrated on the calibration surfaces (0.7.3) its domain holds the part too: under
    ``ROUTE_MAX_OUT_OF_DOMAIN`` of it is outside, so the domain rule alone keeps it as well. (The pose model's card
    has the surfaces' shape domain since 0.8.1: it holds the part about as well.)"""
    from xmetro_ros.parts.study import PRESENTATION
    from xmetro_ros.scan.generated_parts import make_part

    primary, pose = models
    scanner = ScannerModel.load()
    scan = simulate_scan(make_part("step", form_um=40.0).transformed(PRESENTATION), ScanSettings(6.0, 3.0, 0.5),
                         seed=7)
    alone = {m.id: ScanHandler(m, scanner, HandlerParams()).process(scan) for m in (primary, pose)}
    assert _ood(alone[primary.id]) < ROUTE_MAX_OUT_OF_DOMAIN / 2 and _ood(alone[pose.id]) < ROUTE_MAX_OUT_OF_DOMAIN
    both = ScanHandler(primary, scanner, HandlerParams(), pose_model=pose).process(scan)
    assert both.model_id == primary.id
    # the head orientation and the domain rule alone (no orientation given) agree
    h = ScanHandler(primary, scanner, HandlerParams(), pose_model=pose)
    X = alone[primary.id].features
    assert h.route(X) is primary and h.route(X, scan.pose.rotation) is primary
    # the head orientation decides first: a tilted scan's rows, which the domain rule alone sends to the pose model,
    # stay with the primary when the head looked down
    tilted = ScanHandler(primary, scanner, HandlerParams()).process(_scan(rotation_xyz(0.2618, 0.0, 0.0))).features
    assert h.route(tilted) is pose and h.route(tilted, scan.pose.rotation) is primary


def test_core_loads_the_pose_model_only_where_it_belongs(tmp_path):
    from xmetro_ros.ros.core import XmetroCore
    from xmetro_ros.ros.params import PARAMS

    base = {p.name: p.default for p in PARAMS}
    core = XmetroCore(base)
    assert core.pose_model is not None and not core.pose_model_error and not core.search_ensemble_error
    # the shipped search ensemble searches next to the shipped models; 'none': the pose model does
    assert core.search_model is core.search_ensemble and len(core.search_ensemble.members) == 3
    no_ens = XmetroCore({**base, "search_models_dir": "none"})
    assert no_ens.search_ensemble is None and no_ens.search_model is no_ens.pose_model
    assert XmetroCore({**base, "pose_model_dir": "none"}).pose_model is None
    # a search ensemble that cannot load: said, and the search falls back to the pose model
    bad = XmetroCore({**base, "search_models_dir": str(tmp_path / "missing")})
    assert bad.search_model is bad.pose_model and "search ensemble unavailable" in bad.search_ensemble_error
    # a model_dir of one's own (a calibrated scanner) gets no shipped pose model unless asked for
    own = tmp_path / "own"
    shutil.copytree(default_model_dir(), own)
    c2 = XmetroCore({**base, "model_dir": str(own)})
    assert c2.pose_model is None and c2.search_ensemble is None and c2.search_model is c2.model
    # a pose model for other features is refused, and the node judges with the primary alone, saying why
    odd = tmp_path / "odd"
    shutil.copytree(pose_model_dir(), odd)
    card = json.loads((odd / "card.json").read_text())
    card["feature_names"] = list(reversed(card["feature_names"]))
    card["feature_units"] = list(reversed(card["feature_units"]))
    (odd / "card.json").write_text(json.dumps(card))
    c3 = XmetroCore({**base, "pose_model_dir": str(odd)})
    assert c3.model is not None and c3.pose_model is None and "not the primary model's" in c3.pose_model_error
    # its card's recommender calibration: a malformed one is refused at start, a valid one is the search's
    cal = tmp_path / "cal"
    shutil.copytree(pose_model_dir(), cal)
    card = json.loads((cal / "card.json").read_text())
    (cal / "card.json").write_text(json.dumps({**card, "recommend": {"prediction_rel_unc": 0.2}}))
    c4 = XmetroCore({**base, "pose_model_dir": str(cal)})
    assert c4.pose_model is None and "'recommend' block" in c4.pose_model_error
    (cal / "card.json").write_text(json.dumps({**card, "recommend": {"prediction_rel_unc": 0.2,
                                                                     "exposure_u_scale": {"0.5": 1.0}}}))
    c5 = XmetroCore({**base, "pose_model_dir": str(cal)})
    assert c5.search_ensemble is None  # a pose model of one's own is searched with as it is
    assert recommend_calibration(c5.search_model) == RecommendCalibration({0.5: 1.0}, 0.2, "the model card's")


def test_diagnostics_say_which_models_judge():
    from builtin_interfaces.msg import Time

    from xmetro_ros.ros.diagnostics import WARN, DiagnosticsState

    ok = DiagnosticsState("xmetro_node", "xm-ls90", "primary-id", pose_model_id="pose-id")
    values = {kv.key: kv.value for kv in ok.build(Time()).status[0].values}
    assert values["model_id"] == "primary-id" and values["pose_model_id"] == "pose-id"
    bad = DiagnosticsState("xmetro_node", "xm-ls90", "primary-id", pose_model_error="pose model set unavailable: x")
    st = bad.build(Time()).status[0]
    assert bad.level() >= WARN and "pose model set unavailable" in st.message
    assert {kv.key: kv.value for kv in st.values}["pose_model_id"] == "pose model set unavailable: x"
