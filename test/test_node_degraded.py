"""xmetro_node with an unusable model (missing, corrupt, features not computable) or a model needing a field the
cloud lacks: it starts anyway, says why, answers ERROR and success = false; and the real ``xmetro_node`` process
started with config/xmetro.yaml (best-effort scan QoS) judges a scan."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
from rclpy.node import Node
from rclpy.parameter import Parameter
from test_node_helpers import TIMEOUT, NodeClient, cloud_of, settings_msg, sim_scan

from xmetro_ros.msg import ScanQuality
from xmetro_ros.ros.convert import scan_to_cloud
from xmetro_ros.ros.dds_env import fresh_domain_id
from xmetro_ros.ros.node import XmetroNode
from xmetro_ros.ros.rclpy_util import NodeProcess, NodeSpinner, call_service, wait_for
from xmetro_ros.scan.resources import config_path, default_model_dir
from xmetro_ros.srv import Explain, RecommendSettings

S = 1_000_000_000
ERROR = 2


def _model_src() -> Path:
    return Path(os.environ.get("XMETRO_TEST_MODEL_DIR") or default_model_dir())


def _broken(kind: str, tmp: Path) -> Path:
    d = tmp / kind
    if kind == "missing":
        return d
    shutil.copytree(_model_src(), d)
    card = json.loads((d / "card.json").read_text())
    if kind == "corrupt":
        (d / card["models"][0]["file"]).write_bytes(b"this is not an ONNX file")
        card["models"][0].pop("sha256", None)  # reach ONNX Runtime's own failure, not the checksum's
        (d / "card.json").write_text(json.dumps(card))
    elif kind == "unknown_feature":
        card["feature_names"][-1] = "curvature_of_the_moon"
        (d / "card.json").write_text(json.dumps(card))
    elif kind == "needs_field":
        card["feature_names"][-1] = "field_reflectance"
        (d / "card.json").write_text(json.dumps(card))
    return d


def _rig(model_dir: Path):
    node_sp = NodeSpinner(lambda ctx: XmetroNode(context=ctx, parameter_overrides=[
        Parameter("model_dir", value=str(model_dir))]))
    cli_sp = NodeSpinner(lambda ctx: Node("xmetro_tester", context=ctx))
    client = NodeClient(cli_sp.node)
    client.wait_matched(node_sp.node)
    return node_sp, cli_sp, client


@pytest.mark.parametrize("kind,reason", [("missing", "does not exist"), ("corrupt", "cannot load"),
                                         ("unknown_feature", "curvature_of_the_moon")])
def test_unusable_model_node_runs_degraded(tmp_path, kind, reason):
    node_sp, cli_sp, client = _rig(_broken(kind, tmp_path))
    try:
        node = node_sp.node
        assert node.core.model is None and reason in node.core.degraded
        mark = client.diag_mark()
        scan = sim_scan(10 * S)
        client.pub_settings.publish(settings_msg(scan, 9 * S))
        # best-effort scan subscription (the default): a scan published while discovery is still settling may be
        # lost, so it is sent again until answered (a degraded node answers at once)
        q, _, _ = client.send(cloud_of(scan), resend_every=3.0)
        assert q.verdict == ScanQuality.VERDICT_ERROR and q.error_code == ScanQuality.ERROR_MODEL_UNAVAILABLE
        assert reason in q.message and q.model_id == ""
        d = client.wait_diag_level(ERROR, mark)
        assert "degraded" in d.status[0].message and reason in d.status[0].message
        for srv, req in ((Explain, Explain.Request()), (RecommendSettings, RecommendSettings.Request())):
            name = "explain" if srv is Explain else "recommend_settings"
            r = call_service(cli_sp.node.create_client(srv, f"/xmetro_node/{name}"), req, timeout=TIMEOUT)
            assert not r.success and reason in r.message
        assert node._worker.is_alive()
    finally:
        cli_sp.close()
        node_sp.close()


def test_model_needing_a_missing_field(tmp_path):
    node_sp, cli_sp, client = _rig(_broken("needs_field", tmp_path))
    try:
        scan = sim_scan(10 * S)
        scan.fields["reflectance"] = scan.fields["intensity"].copy()
        client.pub_settings.publish(settings_msg(scan, 9 * S))
        assert wait_for(lambda: node_sp.node.core.settings_count >= 1, TIMEOUT)
        q, _, _ = client.send(scan_to_cloud(scan, fields=["intensity"]), outputs=False, resend_every=5.0)
        assert q.error_code == ScanQuality.ERROR_MISSING_INPUT_FIELD and "reflectance" in q.message
        q, dev, _ = client.send(scan_to_cloud(scan, header_stamp=11 * S), resend_every=5.0)
        assert q.error_code == ScanQuality.ERROR_NONE and dev is not None, q.message
    finally:
        cli_sp.close()
        node_sp.close()


def test_node_process_with_params_file():
    """The console entry point as a child process: params file, best-effort scan QoS, a scan judged, clean exit."""
    domain = fresh_domain_id() % 100 + 101  # not the in-process tests' domain
    params = {"reliability": "best_effort"}
    if os.environ.get("XMETRO_TEST_MODEL_DIR"):
        params["model_dir"] = os.environ["XMETRO_TEST_MODEL_DIR"]
    proc = NodeProcess(params_file=str(config_path("xmetro.yaml")), params=params, domain_id=domain)
    proc.start(timeout=60.0)
    old = os.environ.get("ROS_DOMAIN_ID")
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    try:
        cli_sp = NodeSpinner(lambda ctx: Node("xmetro_tester", context=ctx))
    finally:
        if old is None:
            os.environ.pop("ROS_DOMAIN_ID")
        else:
            os.environ["ROS_DOMAIN_ID"] = old
    try:
        client = NodeClient(cli_sp.node, best_effort=True)
        client.wait_matched()
        scan = sim_scan(10 * S)
        client.pub_settings.publish(settings_msg(scan, 9 * S))
        # settings are transient-local: wait until the node has them (its quality then says not defaulted)
        got = None
        for k in range(20):
            msg = cloud_of(sim_scan(10 * S + k, radius=8.0))
            q, dev, _ = client.send(msg, resend_every=2.0)
            if not q.settings_defaulted:
                got = (q, dev)
                break
        assert got is not None
        q, dev = got
        assert q.error_code == ScanQuality.ERROR_NONE and dev.width * dev.height == msg.width * msg.height
    finally:
        cli_sp.close()
        code = proc.stop()
    assert code == 0, "\n".join(proc.lines[-20:])
    assert any("xmetro_node ready" in line for line in proc.lines)


def test_a_model_for_another_scanner_is_refused_unless_allowed(tmp_path):
    """A model set whose card names another scanner leaves the node degraded, saying why; the parameter
    allow_foreign_model overrides. Legacy cards (no scanner) count as the packaged virtual scanner's."""
    import json
    import shutil

    from xmetro_ros.ros.core import XmetroCore, model_scanner_id
    from xmetro_ros.ros.params import PARAMS
    from xmetro_ros.scan.resources import default_model_dir

    model = tmp_path / "model"
    shutil.copytree(default_model_dir(), model)
    card = json.loads((model / "card.json").read_text())
    assert model_scanner_id(card) == "xm-ls90"
    card["scanner"] = {"id": "ls-200", "serial": "SN-7"}
    (model / "card.json").write_text(json.dumps(card))
    values = {p.name: p.default for p in PARAMS} | {"model_dir": str(model)}
    core = XmetroCore(values)
    assert core.model is None and "trained for scanner 'ls-200'" in core.degraded
    assert "allow_foreign_model" in core.degraded
    allowed = XmetroCore(values | {"allow_foreign_model": True})
    assert allowed.model is not None and allowed.degraded == ""
