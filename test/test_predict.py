"""xmetro predict: the live node's processing offline — identical outputs field by field (live node in this process,
same default parameters and model), bags without settings, bad model, and the comparison itself can fail."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
from conftest import need_shared

from xmetro_ros.apps.predict import PredictError, predict_bag
from xmetro_ros.apps.replay import replay_bag
from xmetro_ros.bag.reader import BagReader
from xmetro_ros.ros.node_outputs import EXACT, compare_outputs, deviation_arrays, read_outputs
from xmetro_ros.ros.rclpy_util import NodeSpinner

ROOT = Path(__file__).resolve().parents[1]
BAGS = ROOT / "bags"
TRUCK = ROOT.parent / "shared" / "data" / "bags" / "rosbag2_pointcloud2_truck"


@pytest.fixture(scope="module")
def predicted(tmp_path_factory):
    out = tmp_path_factory.mktemp("predict") / "pred.mcap"
    res = predict_bag(BAGS / "demo.mcap", out)
    return res, out


def test_predict_is_identical_to_the_live_node(predicted, tmp_path):
    from xmetro_ros.ros.node import XmetroNode

    res, out = predicted
    rec = tmp_path / "live.mcap"
    with NodeSpinner(lambda ctx: XmetroNode(context=ctx)):
        live = replay_bag(BAGS / "demo.mcap", fast=True, record=rec)
    assert live.complete and live.scans_sent == len(res.outputs) == 4
    offline, online = read_outputs(out), read_outputs(rec)
    # Every field of every message, exactly (processing_latency aside: it is a wall-clock time).
    assert compare_outputs(offline, online, EXACT) == []
    assert all(o.deviations is not None and o.corrected is not None for o in online)
    # The QoS predict records for the node's outputs is the one the live node offers (replay recorded it from the
    # graph, which carries every policy but history/depth).
    from xmetro_ros.bag.qos import offered_qos_list

    pred, live_bag = BagReader(out), BagReader(rec)
    for topic in ("/xmetro_node/quality", "/xmetro_node/deviations", "/xmetro_node/corrected"):
        (p,), (q,) = offered_qos_list(pred.offered_qos(topic)), offered_qos_list(live_bag.offered_qos(topic))
        assert {k: v for k, v in p.items() if k not in ("history", "depth")} == \
            {k: v for k, v in q.items() if k not in ("history", "depth")}, topic


def test_predict_outputs_are_consistent(predicted):
    res, out = predicted
    outs = read_outputs(out)
    assert len(outs) == 4 and res.settings_seen == 4 and not res.notes and not res.losses
    for o in outs:
        q = o.quality
        assert int(q.error_code) == 0 and not q.settings_defaulted and q.model_id == res.model_id
        pts, dev, flags = deviation_arrays(o.deviations)
        assert len(pts) == q.points_received == o.deviations.width * o.deviations.height
        assert int(np.isfinite(pts).all(axis=1).sum()) == q.points_valid
        assert int(np.count_nonzero(flags[np.isfinite(pts).all(axis=1)])) == q.points_flagged <= q.points_valid
        # corrected = measured − d where there is a prediction (d = the published dx, dy, dz = measured − nominal;
        # deviation_arrays reads them back as the model's target −d; float32 on the wire)
        from xmetro_ros.ros.node_outputs import cloud_arrays

        c, published = cloud_arrays(o.corrected), cloud_arrays(o.deviations)
        ok = np.isfinite(dev).all(axis=1)
        assert ok.any()
        d_mm = np.stack([published[k] for k in ("dx", "dy", "dz")], axis=1).astype(np.float64) * 1e3
        np.testing.assert_array_equal(dev[ok], -d_mm[ok])
        for k, name in enumerate("xyz"):
            np.testing.assert_allclose(c[name][ok] * 1e3, pts[ok, k] - d_mm[ok, k], atol=1e-3)
        a = np.abs(dev[ok]).mean(axis=0) * 1e-3
        np.testing.assert_allclose(np.asarray(q.mean_abs_error), a, rtol=1e-4, atol=1e-12)


def test_comparison_reports_any_difference(predicted):
    _res, out = predicted
    a = read_outputs(out)
    b = copy.deepcopy(a)
    assert compare_outputs(a, b) == []
    data = np.frombuffer(bytes(b[1].deviations.data), dtype=np.uint8).copy()
    # dx of the first valid point: offset of field "dx" in the point.
    dx_off = next(f.offset for f in b[1].deviations.fields if f.name == "dx")
    _pts, dev, _ = deviation_arrays(b[1].deviations)
    j = int(np.flatnonzero(np.isfinite(dev).all(axis=1))[0])
    k = j * b[1].deviations.point_step + dx_off
    data[k:k + 4] = np.frombuffer(np.float32(-dev[j, 0] * 1e-3 + 1e-6).tobytes(), dtype=np.uint8)  # published −t
    b[1].deviations.data = data.tobytes()
    b[2].quality.verdict = 3
    diffs = compare_outputs(a, b)
    assert any("scan 1 deviations.dx" in d for d in diffs), diffs
    assert any("scan 2 quality.verdict" in d for d in diffs), diffs
    assert compare_outputs(a, b[:3])[0].startswith("4 scans != 3 scans")


def test_predict_truck_bag_is_not_a_laser_scan(tmp_path, capsys):
    """Issue 27: a vehicle lidar's street scene in metres (no settings: defaulted) is refused as what it is —
    ERROR_NOT_A_LASER_SCAN, nothing predicted, no ~/deviations or ~/corrected — and `xmetro predict` exits 1 with
    the reason on stderr."""
    from xmetro_ros.apps.cli import main
    from xmetro_ros.msg import ScanQuality

    need_shared(TRUCK)
    res = predict_bag(TRUCK, tmp_path / "truck.mcap")
    assert len(res.outputs) == 3 and res.inputs == ["cloud_1", "cloud_2", "cloud_3"]
    assert any("no xmetro_ros/msg/ScannerSettings" in n for n in res.notes)
    for o in res.outputs:
        q = o.quality
        assert q.settings_defaulted and int(q.error_code) == ScanQuality.ERROR_NOT_A_LASER_SCAN
        assert q.verdict == ScanQuality.VERDICT_ERROR and "not a laser line scan" in q.message and " m " in q.message
        assert o.deviations is None and o.corrected is None
    assert read_outputs(tmp_path / "truck.mcap") and all(o.corrected is None
                                                         for o in read_outputs(tmp_path / "truck.mcap"))
    assert main(["predict", str(TRUCK), "--out", str(tmp_path / "cli.mcap")]) == 1
    err = capsys.readouterr().err
    assert "3 of 3 scans are not laser line scans" in err and "ERROR_NOT_A_LASER_SCAN" in err
    # The defaulted settings are those of the node's parameters (10 pt/mm, 4 profiles/mm, 0.5 ms).
    s = res.outputs[0].quality.settings
    assert (s.lateral_density, s.direction_density, s.exposure_time) == (10000.0, 4000.0, 0.0005)


def test_foreign_scan_reason_on_units_and_ranges():
    """The check itself: our scans pass; the same points ×1000 (mm published as metres) and a cloud 5 m away
    are refused; a few spurious far returns are not enough."""
    from xmetro_ros.judge.scan_handler import FOREIGN_FRACTION, foreign_scan_reason
    from xmetro_ros.scan.artifacts import Sphere
    from xmetro_ros.scan.scanner import ScannerModel, ScanSettings
    from xmetro_ros.sim import simulate_scan

    m = ScannerModel.load()
    scan = simulate_scan(Sphere(22.5), ScanSettings(6.0, 3.0, 0.5), scanner=m, seed=1)
    p = scan.points.reshape(-1, 3)
    p = p[np.isfinite(p).all(axis=1)]
    assert foreign_scan_reason(p, scan.pose, m) == ""
    assert "mm published as metres" in foreign_scan_reason(p * 1000.0, scan.pose, m)
    assert "not a laser line scan" in foreign_scan_reason(p + np.array([0.0, 0.0, 5000.0]), scan.pose, m)
    few = p.copy()
    few[: int(0.5 * FOREIGN_FRACTION * len(p))] = [0.0, 0.0, 1e5]
    assert foreign_scan_reason(few, scan.pose, m) == ""
    assert foreign_scan_reason(p[:0], scan.pose, m) == ""


def test_foreign_scan_reason_takes_each_profiles_own_pose():
    """A head carried sideways along the pass (5 m over the scan: a gantry along a long part; each profile posed by
    its own head pose):
    judged from the first pose alone most points lie far outside the measuring range; from their own profiles'
    poses, none does."""
    from xmetro_ros.judge.scan_handler import foreign_scan_reason
    from xmetro_ros.scan.artifacts import Sphere
    from xmetro_ros.scan.geometry import RowPoses
    from xmetro_ros.scan.scanner import ScannerModel, ScanSettings
    from xmetro_ros.sim import simulate_scan

    m = ScannerModel.load()
    scan = simulate_scan(Sphere(22.5), ScanSettings(6.0, 3.0, 0.5), scanner=m, seed=1)
    h, w, _ = scan.points.shape
    shift = np.zeros((h, 3))
    shift[:, 0] = np.linspace(0.0, 5000.0, h)  # row i's head and points moved together
    pts = scan.points + shift[:, None, :]
    poses = RowPoses(positions=np.asarray(scan.pose.position) + shift,
                     rotations=np.repeat(np.asarray(scan.pose.rotation)[None], h, axis=0),
                     rows=np.repeat(np.arange(h, dtype=np.int32)[:, None], w, axis=1))
    valid = np.isfinite(pts).all(axis=2).reshape(-1)
    p = pts.reshape(-1, 3)[valid]
    assert "not a laser line scan" in foreign_scan_reason(p, scan.pose, m)
    assert foreign_scan_reason(p, scan.pose, m, (poses.rows.reshape(-1)[valid], poses)) == ""


def test_predict_refuses_bad_model_and_bad_params(tmp_path):
    with pytest.raises(PredictError, match="no usable model"):
        predict_bag(BAGS / "demo.mcap", tmp_path / "a.mcap", model_dir=tmp_path / "nope")
    with pytest.raises(PredictError, match="unknown node parameter"):
        predict_bag(BAGS / "demo.mcap", tmp_path / "b.mcap", params={"tolerence": 1})
    with pytest.raises(PredictError, match="outside"):
        predict_bag(BAGS / "demo.mcap", tmp_path / "c.mcap", params={"tolerance": 5.0})


def test_cli_predict(tmp_path, capsys):
    from xmetro_ros.apps.cli import main

    out = tmp_path / "p.mcap"
    assert main(["predict", str(BAGS / "regression.mcap"), "--out", str(out), "--param", "tolerance=0.0002"]) == 0
    text = capsys.readouterr().out
    assert "4 scans, 4 settings" in text and out.exists()
    assert main(["predict", str(BAGS / "regression.mcap"), "--out", str(out)]) == 1  # exists: refused
    assert "already exists" in capsys.readouterr().err


def test_a_damaged_bag_is_an_error_unless_allow_partial(tmp_path, capsys):
    """Issue 27: a truncated bag → exit 1 with the reason on stderr (the output still holds every readable scan);
    ``--allow-partial`` → exit 0 with the same output and the LOSS lines."""
    from xmetro_ros.apps.cli import main

    data = (BAGS / "demo.mcap").read_bytes()
    bag = tmp_path / "truncated.mcap"
    bag.write_bytes(data[: len(data) // 2])
    assert main(["predict", str(bag), "--out", str(tmp_path / "a.mcap"), "--deterministic"]) == 1
    cap = capsys.readouterr()
    assert "LOSS:" in cap.out and "lost data" in cap.err and "--allow-partial" in cap.err
    assert main(["predict", str(bag), "--out", str(tmp_path / "b.mcap"), "--deterministic", "--allow-partial"]) == 0
    assert "LOSS:" in capsys.readouterr().out
    a, b = read_outputs(tmp_path / "a.mcap"), read_outputs(tmp_path / "b.mcap")
    assert 0 < len(a) == len(b) < 4
