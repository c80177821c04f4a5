"""xmetro_node with ``profile_input`` over localhost DDS: a driver's profiles (sam-xl/scancontrol's layout, its QoS)
posed by /tf and /tf_static are assembled in the fixed frame and judged like the virtual scanner's own organized
scan of the same pass; tf that is missing, not connected or too old, profiles out of order and a pass cut by a pause
each get their own ScanQuality error code and a /diagnostics WARN, and the next good pass is judged; the stream's
accounting balances (received = judged + dropped + waiting)."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from driver_emulators import DRIVERS
from geometry_msgs.msg import TransformStamped
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger
from stream_rig import HAND_EYE_R, HAND_EYE_T, SimPass, sim_pass
from test_node_helpers import TIMEOUT, NodeClient, settings_msg, stamp_ns_of
from tf2_msgs.msg import TFMessage

from xmetro_ros.judge.inference import ModelSet
from xmetro_ros.judge.scan_handler import ScanHandler
from xmetro_ros.msg import ScanQuality
from xmetro_ros.ros.cloud import xyz_fields
from xmetro_ros.ros.node import XmetroNode
from xmetro_ros.ros.params import handler_params
from xmetro_ros.ros.rclpy_util import NodeSpinner, call_service, wait_for
from xmetro_ros.scan.artifacts import Sphere
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings
from xmetro_ros.sim import simulate_scan

S = 1_000_000_000
SETTINGS = ScanSettings(6.0, 3.0, 0.5)


def _tf(parent: str, child: str, stamp_ns: int, m: np.ndarray) -> TransformStamped:
    t = TransformStamped()
    t.header.frame_id, t.child_frame_id = parent, child
    t.header.stamp = Time(sec=int(stamp_ns // S), nanosec=int(stamp_ns % S))
    t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = (float(v) for v in m[:3, 3])
    q = Rotation.from_matrix(m[:3, :3]).as_quat()
    r = t.transform.rotation
    r.x, r.y, r.z, r.w = (float(v) for v in q)
    return t


class Driver:
    """A line-scanner driver and a robot: profiles on ``profiles`` (sam-xl's layout and QoS), tf at 250 Hz."""

    def __init__(self, node: Node) -> None:
        drv = DRIVERS["scancontrol_samxl"]
        self.builder = drv.builder
        self.pub = node.create_publisher(PointCloud2, "profiles", drv.qos)
        self.pub_tf = node.create_publisher(TFMessage, "/tf", QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.VOLATILE))
        self.pub_static = node.create_publisher(TFMessage, "/tf_static", QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL))

    def static(self, child: str = "sensor", parent: str = "flange") -> None:
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = HAND_EYE_R, HAND_EYE_T
        self.pub_static.publish(TFMessage(transforms=[_tf(parent, child, 0, m)]))

    def tf(self, sp: SimPass, parent: str = "artifact") -> None:
        stamps = sp.tf_stamps()
        mats = sp.flange(stamps)
        for i in range(0, len(stamps), 25):  # 25 samples a message (a robot driver's batch at 250 Hz: 0.1 s)
            self.pub_tf.publish(TFMessage(transforms=[_tf(parent, "flange", int(s), m)
                                                      for s, m in zip(stamps[i:i + 25], mats[i:i + 25], strict=True)]))

    def profiles(self, sp: SimPass, frame: str = "sensor", rows=None, stamp_offset: int = 0) -> int:
        """Publish the pass's profiles at about 1 kHz; returns how many."""
        rows = range(len(sp.stamps_ns)) if rows is None else rows
        n = 0
        for i in rows:
            em = self.builder(sp.profiles[i].astype(np.float64), int(sp.stamps_ns[i]) + stamp_offset, frame_id=frame)
            self.pub.publish(em.msg)
            n += 1
            time.sleep(0.001)
        return n


@pytest.fixture(scope="module")
def rig():
    scanner = ScannerModel.load()
    overrides = [Parameter("profile_input", value=True), Parameter("fixed_frame", value="artifact"),
                 Parameter("scan_trigger", value="gap"), Parameter("trigger_gap", value=0.3),
                 Parameter("tf_timeout", value=0.3), Parameter("min_valid_points", value=50),
                 Parameter("model_dir", value=os.environ.get("XMETRO_TEST_MODEL_DIR", ""))]
    node_sp = NodeSpinner(lambda ctx: XmetroNode(context=ctx, parameter_overrides=overrides), threads=2)
    cli_sp = NodeSpinner(lambda ctx: Node("driver_and_robot", context=ctx))
    client = NodeClient(cli_sp.node)
    driver = Driver(cli_sp.node)
    try:
        node = node_sp.node
        assert wait_for(lambda: driver.pub.get_subscription_count() > 0 and driver.pub_tf.get_subscription_count() > 0
                        and driver.pub_static.get_subscription_count() > 0
                        and node.pub_quality.get_subscription_count() > 0
                        and node.pub_dev.get_subscription_count() > 0, TIMEOUT)
        yield node, client, driver, cli_sp.node, scanner
    finally:
        cli_sp.close()
        node_sp.close()


def _quality(client: NodeClient, pred, timeout: float = TIMEOUT) -> ScanQuality:
    def find():
        with client.lock:
            return next((q for q in client.quality if pred(q)), None)
    assert wait_for(lambda: find() is not None, timeout), \
        f"no such ScanQuality; got {[(q.error_code, q.message[:80]) for q in client.quality][-6:]}"
    return find()


def _diag_values(client: NodeClient) -> dict[str, str]:
    """The key/values of the latest /diagnostics message; {} until one arrived (the node publishes it every
    diagnostics_period: a loaded machine may not have delivered the first yet)."""
    with client.lock:
        if not client.diagnostics:
            return {}
        arr = client.diagnostics[-1][1]
    return {kv.key: kv.value for kv in arr.status[0].values}


def _reference(node: XmetroNode, sp: SimPass):
    """The virtual scanner's organized scan of the pass with the points the driver sent (sensor y = 0, float32 m),
    in the fixed frame as float32 metres (what the node judges), judged from its one start pose."""
    from dataclasses import replace

    loc = sp.profiles.astype(np.float64)
    loc[..., 1] = 0.0  # line-scanner drivers write y = 0: the laser plane
    pts = np.einsum("hwj,hij->hwi", loc, sp.sensor_poses[:, :3, :3]) + sp.sensor_poses[:, None, :3, 3]
    pts = pts.astype(np.float32).astype(np.float64) * 1000.0
    pts[:, -2:] = np.nan  # sam-xl's last two points are always +inf
    scan = replace(sp.scan, points=pts)
    model = ModelSet.load(node.core.values["model_dir"] or None, threads=node.core.values["inference_threads"])
    return scan, ScanHandler(model, ScannerModel.load(), handler_params(node.core.values)).process(scan)


def _pass(client: NodeClient, driver: Driver, scan, sp: SimPass, settings_stamp: int | None) -> tuple[int, ScanQuality]:
    """A pass as a cell runs it: (the settings,) the hand-eye, the robot's tf, then the driver's profiles; returns
    how many profiles were sent and the ScanQuality of the scan they make."""
    if settings_stamp is not None:
        client.pub_settings.publish(settings_msg(scan, settings_stamp))
    driver.static()
    driver.tf(sp)
    time.sleep(0.3)
    n = driver.profiles(sp)
    return n, _quality(client, lambda q: stamp_ns_of(q) == int(sp.stamps_ns[0]))


def test_driver_profiles_posed_by_tf_are_judged_like_the_organized_scan(rig):
    node, client, driver, _cli, scanner = rig
    scan = simulate_scan(Sphere(17.5, np.zeros(3)), SETTINGS, seed=4)
    sp = sim_pass(scan, scanner, t0_ns=100 * S)
    n, q = _pass(client, driver, scan, sp, 99 * S)
    assert q.error_code == 0, q.message
    assert q.verdict == ScanQuality.VERDICT_OK, q.message
    assert f"assembled from {n} profiles" in q.message and "settings from scanner_settings" in q.message
    assert q.header.frame_id == "artifact" and not q.settings_defaulted
    assert wait_for(lambda: client._find("deviations", int(sp.stamps_ns[0])) is not None, TIMEOUT)
    dev = client._find("deviations", int(sp.stamps_ns[0]))
    assert (dev.height, dev.width) == scan.shape[:2]
    names = ["dx", "dy", "dz", "ux", "uy", "uz", "flags"]
    xyz, f = xyz_fields(dev, names)
    ref_scan, ref = _reference(node, sp)
    # the same points, within the float32 metres the driver sent
    v = ref_scan.valid_mask()
    np.testing.assert_allclose(np.asarray(xyz, float)[v] * 1000.0, ref_scan.points.reshape(-1, 3)[v], atol=1e-4)
    flags = np.asarray(f["flags"]).astype(np.uint16)
    assert (flags == ref.flags).mean() >= 0.999
    d = np.stack([f[k] for k in ("dx", "dy", "dz")], axis=1).astype(float)
    u = np.stack([f[k] for k in ("ux", "uy", "uz")], axis=1).astype(float)
    both = np.isfinite(d).all(axis=1) & np.isfinite(ref.deviations).all(axis=1)
    assert both.sum() > 0.5 * v.sum()
    # published d = measured - nominal (the model's target turned once): -t
    assert np.abs(d[both] + ref.deviations[both] / 1000.0).max() < 1e-7  # 0.1 µm
    assert np.abs(u[both] - ref.uncertainty[both] / 1000.0).max() < 1e-7
    assert wait_for(lambda: int(_diag_values(client).get("profiles_judged", 0)) >= n, TIMEOUT), _diag_values(client)


def test_tf_problems_each_get_their_code_and_the_next_pass_is_judged(rig):
    _node, client, driver, _cli, scanner = rig
    scan = simulate_scan(Sphere(17.5, np.zeros(3)), SETTINGS, seed=5)
    codes = ScanQuality
    # 1) a sensor frame nobody publishes: TF_MISSING after tf_timeout
    sp = sim_pass(scan, scanner, t0_ns=200 * S)
    driver.tf(sp)
    driver.profiles(sp, frame="ghost_sensor", rows=range(20))
    q = _quality(client, lambda q: q.error_code == codes.ERROR_TF_MISSING)
    assert "TF_MISSING" in q.message and q.header.frame_id == "ghost_sensor"
    # 2) a frame known to tf but not joined to the fixed frame: TF_NOT_CONNECTED
    island = np.eye(4)
    driver.pub_static.publish(TFMessage(transforms=[_tf("island", "island_sensor", 0, island)]))
    sp2 = sim_pass(scan, scanner, t0_ns=210 * S)
    driver.tf(sp2)
    time.sleep(0.2)
    driver.profiles(sp2, frame="island_sensor", rows=range(20))
    _quality(client, lambda q: q.error_code == codes.ERROR_TF_NOT_CONNECTED)
    # 3) profiles whose tf never comes: TF_LATE
    sp3 = sim_pass(scan, scanner, t0_ns=400 * S)
    driver.profiles(sp3, rows=range(20))
    _quality(client, lambda q: q.error_code == codes.ERROR_TF_LATE)
    # 4) out of order: a profile older than the previous one
    sp4 = sim_pass(scan, scanner, t0_ns=220 * S)
    driver.tf(sp4)
    time.sleep(0.2)
    driver.profiles(sp4, rows=[10, 5])
    _quality(client, lambda q: q.error_code == codes.ERROR_PROFILE_OUT_OF_ORDER)
    # the node is alive: the next good pass is judged
    sp5 = sim_pass(scan, scanner, t0_ns=500 * S)
    client.pub_settings.publish(settings_msg(scan, 499 * S))
    driver.tf(sp5)
    time.sleep(0.3)
    driver.profiles(sp5)
    q = _quality(client, lambda q: stamp_ns_of(q) == int(sp5.stamps_ns[0]))
    assert q.error_code == 0 and q.verdict in (ScanQuality.VERDICT_OK, ScanQuality.VERDICT_WARN), q.message
    # accounting: received = judged + dropped + waiting, and /diagnostics warned
    def balanced() -> bool:
        v = _diag_values(client)
        if "profiles_received" not in v:
            return False
        return int(v["profiles_received"]) == int(v["profiles_judged"]) + int(v["profiles_dropped"]) \
            + int(v["profiles_waiting"]) and int(v["profiles_waiting"]) == 0
    assert wait_for(balanced, TIMEOUT), _diag_values(client)
    v = _diag_values(client)
    assert "tf_missing" in v["profiles_dropped_by_reason"] and "out_of_order" in v["profiles_dropped_by_reason"]


def test_a_failing_stream_callback_is_logged_and_the_stream_goes_on(rig):
    """A callback of the profile input that raises (here the stream's tf intake, once) is logged with its cause,
    and the helper's executor keeps spinning: the next pass is judged (rclpy's spin() would have ended there, and
    every profile after it would have been lost without a word)."""
    node, client, driver, _cli, scanner = rig
    real_tf, calls = node.stream.tf, []

    def failing_once(*args, **kwargs):
        if not calls:
            calls.append(1)
            raise RuntimeError("injected tf intake failure")
        return real_tf(*args, **kwargs)

    node.stream.tf = failing_once
    try:
        # the failure hits a transform of no use to the pass, so that the pass itself is whole
        driver.pub_tf.publish(TFMessage(transforms=[_tf("artifact", "elsewhere", 600 * S, np.eye(4))]))
        assert wait_for(lambda: bool(calls), TIMEOUT)
        # on /diagnostics (a WARN with the cause); also logged at ERROR, which /rosout does not always deliver here
        text = "a callback failed and was skipped: RuntimeError: injected tf intake failure"

        def warned() -> bool:
            with client.lock:
                return any(st.level >= st.WARN and text in st.message for _s, d in client.diagnostics[-20:]
                           for st in d.status)
        assert wait_for(warned, TIMEOUT)
        scan = simulate_scan(Sphere(17.5, np.zeros(3)), SETTINGS, seed=8)
        sp = sim_pass(scan, scanner, t0_ns=600 * S)
        _n, q = _pass(client, driver, scan, sp, 599 * S)
        assert q.error_code == 0, q.message
    finally:
        del node.stream.tf


def test_signal_trigger_service_refused_with_reason_on_a_gap_trigger(rig):
    _node, _client, _driver, cli, _scanner = rig
    c = cli.create_client(Trigger, "/xmetro_node/start_scan")
    res = call_service(c, Trigger.Request(), timeout=TIMEOUT)
    assert not res.success and "signal trigger" in res.message


def test_recorded_profiles_and_tf_predict_offline_like_the_live_node(rig, tmp_path):
    """xmetro record (the Recorder) of the driver's profiles, /tf, /tf_static and the settings → xmetro predict
    with profile_input: the same scan, the same deviations as the live node published."""
    from xmetro_ros.apps.predict import predict_bag
    from xmetro_ros.bag.reader import BagReader
    from xmetro_ros.bag.writer import BagWriter
    from xmetro_ros.ros.recorder import Recorder

    node, client, driver, _cli, scanner = rig
    scan = simulate_scan(Sphere(17.5, np.zeros(3)), SETTINGS, seed=6)
    sp = sim_pass(scan, scanner, t0_ns=700 * S)
    bag = tmp_path / "profiles.mcap"
    rec_sp = NodeSpinner(lambda ctx: Node("recorder", context=ctx))
    writer = BagWriter(bag)
    try:
        rec = Recorder(rec_sp.node, writer, ["/profiles", "/tf", "/tf_static", "/scanner_settings"],
                       discovery_period=0.2)
        assert wait_for(lambda: len(rec.subscriptions) == 4, TIMEOUT), rec.subscriptions
        time.sleep(0.5)
        n, live = _pass(client, driver, scan, sp, 699 * S)
        assert wait_for(lambda: rec.counts["/profiles"] == n, TIMEOUT), rec.counts
        rec.close()
    finally:
        writer.close()
        rec_sp.close()
    res = predict_bag(bag, tmp_path / "judged.mcap", params={
        "profile_input": True, "fixed_frame": "artifact", "scan_trigger": "gap", "trigger_gap": 0.3,
        "min_valid_points": 50, "model_dir": node.core.values["model_dir"]})
    mine = [o for o in res.outputs if stamp_ns_of(o.quality) == int(sp.stamps_ns[0])]
    assert len(mine) == 1, [o.quality.message for o in res.outputs]
    q = mine[0].quality
    assert (q.verdict, q.error_code) == (live.verdict, live.error_code)
    # the bag ends before the pause that ended the live scan: offline, the bag's end closes it
    assert q.message.replace("(end FLUSH)", "(end GAP)") == live.message
    live_dev = client._find("deviations", int(sp.stamps_ns[0]))
    assert bytes(mine[0].deviations.data) == bytes(live_dev.data)
    topics = BagReader(tmp_path / "judged.mcap").topics()
    assert {"/profiles", "/tf", "/tf_static", "/xmetro_node/quality"} <= set(topics)


def test_settings_from_the_driver_parameters_and_measured_densities(rig):
    """No ScannerSettings: the exposure comes from the driver's own parameter (IGMR-RWTH/scancontrol_lls's
    ``exposure_time``, µs, followed on /parameter_events), the densities are measured from the posed profiles."""
    _node, _client, driver, _cli, scanner = rig
    # the driver's writers must see this node's readers before it publishes: a reader that has matched a writer
    # (sub_profiles.get_publisher_count()) may not yet be matched by it, and then gets nothing (one CI run)
    seen = {p: p.get_subscription_count() for p in (driver.pub, driver.pub_tf, driver.pub_static)}
    drv_sp = NodeSpinner(lambda ctx: Node("lls_driver_t", context=ctx))
    drv_sp.node.declare_parameter("exposure_time", 2000)
    drv_sp.node.declare_parameter("profile_period", 10000)
    overrides = [Parameter("profile_input", value=True), Parameter("fixed_frame", value="artifact"),
                 Parameter("scan_trigger", value="gap"), Parameter("trigger_gap", value=0.3),
                 Parameter("min_valid_points", value=50), Parameter("driver_mapping", value="scancontrol_lls"),
                 Parameter("driver_node", value="/lls_driver_t"),
                 Parameter("model_dir", value=os.environ.get("XMETRO_TEST_MODEL_DIR", ""))]
    node_sp = NodeSpinner(lambda ctx: XmetroNode("xmetro_driven", context=ctx, parameter_overrides=overrides),
                          threads=2)
    lis_sp = NodeSpinner(lambda ctx: Node("listener_driven", context=ctx))
    client = NodeClient(lis_sp.node, target="xmetro_driven")
    try:
        node = node_sp.node
        assert wait_for(lambda: node._driver_values == {"exposure_ms": 2.0}, TIMEOUT), node._driver_values
        assert wait_for(lambda: node.pub_quality.get_subscription_count() > 0
                        and node.sub_profiles.get_publisher_count() > 0
                        and all(p.get_subscription_count() > n for p, n in seen.items()), TIMEOUT)
        scan = simulate_scan(Sphere(17.5, np.zeros(3)), SETTINGS, seed=7)
        # stamped before every ScannerSettings the rig published (transient local: this node gets them too)
        for k, t0 in enumerate((50 * S, 60 * S)):
            if k == 1:  # the driver's parameter changes: followed for the next scan
                drv_sp.node.set_parameters([Parameter("exposure_time", value=500)])
                assert wait_for(lambda: node._driver_values == {"exposure_ms": 0.5}, TIMEOUT)
            _n, q = _pass(client, driver, scan, sim_pass(scan, scanner, t0_ns=t0), None)
            assert q.error_code == 0, q.message
            assert "exposure driver" in q.message and "lateral_density, direction_density measured" in q.message
            assert not q.settings_defaulted
            assert q.settings.exposure_time == pytest.approx((2.0, 0.5)[k] * 1e-3)
            assert q.settings.direction_density == pytest.approx(SETTINGS.direction_density * 1000, rel=1e-6)
            assert q.settings.lateral_density == pytest.approx(SETTINGS.lateral_density * 1000, rel=3e-3)
    finally:
        lis_sp.close()
        node_sp.close()
        drv_sp.close()
