"""A model whose card lists a per-point field feature (``field_intensity``, as the closed loop exports): replayed
through a live node, the node reads the field from the PointCloud2 — the explained feature values are the cloud's
intensities — and a cloud without the field is refused with ERROR_MISSING_INPUT_FIELD.

The model dir is built here with LEARN's export API (``fit_model`` + ``export_model_set``, the calls LOOP's
``export_loop_model`` makes) from one simulated scan, so the test does not depend on running the loop.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from xmetro_ros.bag.reader import BagReader
from xmetro_ros.msg import ScanQuality
from xmetro_ros.predict import cloud_arrays
from xmetro_ros.replay import replay_bag
from xmetro_ros.ros_util import NodeSpinner, call_service

ROOT = Path(__file__).resolve().parents[1]
BAGS = ROOT / "bags"
TRUCK = ROOT.parent / "shared" / "data" / "bags" / "rosbag2_pointcloud2_truck"


@pytest.fixture(scope="module")
def field_model(tmp_path_factory) -> Path:
    from xmetro_ros.artifacts import Sphere
    from xmetro_ros.features import STUDY_FEATURES, FeatureContext, compute_features
    from xmetro_ros.learn.train import export_model_set, fit_model
    from xmetro_ros.preprocess import prepare_scan
    from xmetro_ros.scanner import ScanSettings
    from xmetro_ros.sim import simulate_scan

    names = [*STUDY_FEATURES, "field_intensity"]
    scan = simulate_scan(Sphere(radius=22.5), ScanSettings(6.0, 3.0, 0.5), seed=3)
    prep = prepare_scan(scan)
    X = compute_features(names, FeatureContext.from_prepared(prep))
    y = scan.artifact.errors(prep.points)
    models = [fit_model("dt", X, y[:, a], seed=0, axes=(a,), params={"max_depth": 4}) for a in range(3)]
    out = export_model_set(models, tmp_path_factory.mktemp("model") / "field_model", feature_names=names,
                           X_train=X, model_id="test-dt-field_intensity")
    assert "field_intensity" in json.loads((out / "card.json").read_text())["feature_names"]
    return out


@pytest.fixture(scope="module")
def node(field_model):
    from rclpy.parameter import Parameter

    from xmetro_ros.node import XmetroNode

    with NodeSpinner(lambda ctx: XmetroNode(context=ctx, parameter_overrides=[
            Parameter("model_dir", value=str(field_model))])) as sp:
        assert sp.node.core.model_id == "test-dt-field_intensity", sp.node.core.degraded
        yield sp


def test_node_reads_field_from_pointcloud2(node):
    from rclpy.node import Node

    from xmetro_ros.srv import Explain

    res = replay_bag(BAGS / "regression.mcap", fast=True)
    assert res.complete and res.scans_sent == 4
    assert all(int(s.quality.error_code) == 0 and s.quality.model_id == "test-dt-field_intensity"
               for s in res.scans)
    clouds = [m.msg for m in BagReader(BAGS / "regression.mcap").messages(topics=["/scan"])]
    intensity = cloud_arrays(clouds[-1])["intensity"]
    valid = np.flatnonzero(np.isfinite(cloud_arrays(clouds[-1])["x"]))
    ask = valid[:: max(1, len(valid) // 50)][:50]
    with NodeSpinner(lambda ctx: Node("field_client", context=ctx)) as cl:
        client = cl.node.create_client(Explain, "/xmetro_node/explain")
        req = Explain.Request()  # scan_stamp 0 = the latest judged scan (the last one replayed)
        req.indices = [int(i) for i in ask]
        r = call_service(client, req, timeout=60.0)
    assert r.success, r.message
    names = list(r.feature_names)
    F = len(names)
    fv = np.asarray(r.feature_values).reshape(-1, F)
    idx = np.asarray(r.point_indices, dtype=np.int64)
    assert len(idx) > 10 and set(idx) <= set(ask.tolist())
    np.testing.assert_array_equal(fv[:, names.index("field_intensity")].astype(np.float32), intensity[idx])
    assert np.ptp(fv[:, names.index("field_intensity")]) > 0


def test_cloud_without_the_field_is_refused(node):
    res = replay_bag(TRUCK, fast=True, topics=["cloud_2"])
    q = res.scans[0].quality
    assert int(q.error_code) == ScanQuality.ERROR_MISSING_INPUT_FIELD and q.verdict == ScanQuality.VERDICT_ERROR
    assert "intensity" in q.message
