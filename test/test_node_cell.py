"""The node in a real cell, over real DDS (the test harness's private namespace): best-effort scanner drivers,
volatile settings publishers, ROS 2's standard QoS override parameters, and the caller's DDS environment honoured
(a node started with only ``ROS_DOMAIN_ID=0`` is seen on domain 0)."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from test_node_helpers import TIMEOUT, NodeClient, cloud_of, settings_msg, sim_scan

from xmetro_ros.msg import ScannerSettings, ScanQuality
from xmetro_ros.ros.dds_env import DDS_ENV_KEYS, LOCALHOST_ONLY_ENV
from xmetro_ros.ros.node import XmetroNode
from xmetro_ros.ros.rclpy_util import NodeProcess, NodeSpinner, wait_for

S = 1_000_000_000


def _volatile_settings_pub(node: Node):
    """What ``ros2 topic pub`` (and ``ros2 bag play`` of a bag without QoS metadata) offers: reliable, volatile."""
    return node.create_publisher(ScannerSettings, "scanner_settings", QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE))


@pytest.fixture(scope="module")
def default_node():
    """The node with its default QoS (no reliability / override parameter)."""
    sp = NodeSpinner(lambda ctx: XmetroNode(context=ctx, parameter_overrides=[
        Parameter("min_valid_points", value=50)]))
    tester = NodeSpinner(lambda ctx: Node("xmetro_cell_tester", context=ctx))
    try:
        yield sp.node, tester.node
    finally:
        tester.close()
        sp.close()


def test_best_effort_scans_and_volatile_settings_are_used(default_node):
    node, tester = default_node
    assert node.sub_scan.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
    client = NodeClient(tester, best_effort=True)  # a scanner driver: sensor-data QoS (best effort)
    pub_vol = _volatile_settings_pub(tester)
    assert wait_for(lambda: client.pub_scan.get_subscription_count() > 0 and pub_vol.get_subscription_count() > 0
                    and all(s.get_publisher_count() > 0 for s in client.subs), TIMEOUT)
    base = sim_scan(100 * S)
    n0 = node.core.settings_count
    pub_vol.publish(settings_msg(base, 95 * S))
    assert wait_for(lambda: node.core.settings_count == n0 + 1, TIMEOUT), "volatile settings never arrived"
    q, dev, _corr = client.send(cloud_of(base), resend_every=2.0)
    assert not q.settings_defaulted, q.message  # the volatile publisher's settings were used
    assert dev is not None and dev.width * dev.height == base.points.reshape(-1, 3).shape[0]
    # A transient-local publisher matches both settings subscriptions: its message is stored once.
    client.pub_settings.publish(settings_msg(base, 96 * S))
    assert wait_for(lambda: node.core.settings_count == n0 + 2, TIMEOUT)
    time.sleep(1.0)
    assert node.core.settings_count == n0 + 2
    # A reliable scan publisher is matched too (best-effort subscription).
    rel = tester.create_publisher(PointCloud2, "scan", QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE))
    assert wait_for(lambda: rel.get_subscription_count() > 0, TIMEOUT)


def test_late_joiner_gets_latched_settings(default_node):
    """Settings latched (transient-local) before the node's subscription existed still reach it."""
    _node, tester = default_node
    latched = tester.create_publisher(ScannerSettings, "/late/scanner_settings", QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL))
    latched.publish(settings_msg(sim_scan(200 * S), 199 * S))
    late = NodeSpinner(lambda ctx: XmetroNode(context=ctx, parameter_overrides=[
        Parameter("min_valid_points", value=50)], cli_args=["--ros-args", "-r", "__ns:=/late"]))
    try:
        assert wait_for(lambda: late.node.core.settings_count == 1, TIMEOUT)
        time.sleep(1.0)
        assert late.node.core.settings_count == 1  # delivered to both subscriptions, stored once
    finally:
        late.close()


def test_qos_override_parameters_change_the_subscriptions():
    overrides = [Parameter("qos_overrides./ovr/scan.subscription.reliability", value="reliable"),
                 Parameter("qos_overrides./ovr/scanner_settings.subscription_volatile.depth", value=3)]
    sp = NodeSpinner(lambda ctx: XmetroNode(context=ctx, parameter_overrides=overrides,
                                            cli_args=["--ros-args", "-r", "__ns:=/ovr"]))
    tester = NodeSpinner(lambda ctx: Node("xmetro_ovr_tester", context=ctx))
    try:
        node = sp.node
        assert node.sub_scan.qos_profile.reliability == ReliabilityPolicy.RELIABLE
        assert node.sub_settings_volatile.qos_profile.depth == 3
        assert node.get_parameter("qos_overrides./ovr/scan.subscription.reliability").value == "reliable"
        # Over DDS: a reliable publisher matches, a best-effort one no longer does.
        rel = tester.node.create_publisher(PointCloud2, "/ovr/scan", QoSProfile(
            depth=5, reliability=ReliabilityPolicy.RELIABLE))
        be = tester.node.create_publisher(PointCloud2, "/ovr/scan", QoSProfile(
            depth=5, reliability=ReliabilityPolicy.BEST_EFFORT))
        assert wait_for(lambda: rel.get_subscription_count() == 1, TIMEOUT)
        time.sleep(1.0)
        assert be.get_subscription_count() == 0
    finally:
        tester.close()
        sp.close()


def test_outputs_and_inputs_are_remappable():
    """issue 11: the node's topics remap like any node's — outputs by their private names (``~/deviations``,
    ``~/quality``, ``~/corrected``), inputs by theirs — and the node then publishes only on the remapped names."""
    remaps = {"scan": "/cell3/points", "scanner_settings": "/cell3/settings", "~/deviations": "/cell3/dev",
              "~/quality": "/cell3/q", "~/corrected": "/cell3/corrected"}
    args = ["--ros-args", "-r", "__node:=xmetro_remapped"]
    for a, b in remaps.items():
        args += ["-r", f"{a}:={b}"]
    sp = NodeSpinner(lambda ctx: XmetroNode(context=ctx, cli_args=args, parameter_overrides=[
        Parameter("min_valid_points", value=50)]))
    tester = NodeSpinner(lambda ctx: Node("xmetro_remap_tester", context=ctx))
    got: dict[str, list] = {"q": [], "dev": [], "corrected": []}
    try:
        t = tester.node
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
        subs = [t.create_subscription(ScanQuality, "/cell3/q", got["q"].append, qos),
                t.create_subscription(PointCloud2, "/cell3/dev", got["dev"].append, qos),
                t.create_subscription(PointCloud2, "/cell3/corrected", got["corrected"].append, qos)]
        pub_scan = t.create_publisher(PointCloud2, "/cell3/points", qos)
        pub_settings = t.create_publisher(ScannerSettings, "/cell3/settings", QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL))
        assert wait_for(lambda: all(s.get_publisher_count() == 1 for s in subs)
                        and pub_scan.get_subscription_count() == 1 and pub_settings.get_subscription_count() == 2,
                        TIMEOUT), "the remapped topics never matched"
        # nothing of the node's is left on the names it would have without the remapping (endpoints filtered by node
        # name: other tests' nodes in this DDS domain may still be in the graph while their removal propagates)
        def ours(infos: list) -> list:
            return [i for i in infos if i.node_name == "xmetro_remapped"]

        # An endpoint can be discovered before its participant's node list: its node name reads "_NODE_NAME_UNKNOWN_"
        # until that arrives, so wait for the name on the remapped topic before the negative checks mean anything.
        assert wait_for(lambda: ours(t.get_subscriptions_info_by_topic("/cell3/points")), TIMEOUT), \
            "the remapped scan subscription is not seen"
        for name in ("/xmetro_remapped/quality", "/xmetro_remapped/deviations", "/xmetro_remapped/corrected"):
            assert ours(t.get_publishers_info_by_topic(name)) == [], name
        for name in ("/scan", "/scanner_settings", "/xmetro_remapped/scan"):
            assert ours(t.get_subscriptions_info_by_topic(name)) == [], name
        base = sim_scan(300 * S)
        pub_settings.publish(settings_msg(base, 299 * S))
        assert wait_for(lambda: sp.node.core.settings_for(300 * S) is not None, TIMEOUT), "settings never arrived"
        deadline = time.monotonic() + TIMEOUT
        while time.monotonic() < deadline:  # the scan subscription is best effort: resend until answered
            pub_scan.publish(cloud_of(base))
            if wait_for(lambda: got["q"] and got["dev"] and got["corrected"], 2.0):
                break
        assert got["q"] and got["dev"] and got["corrected"], {k: len(v) for k, v in got.items()}
        q = got["q"][0]
        assert q.error_code == ScanQuality.ERROR_NONE and not q.settings_defaulted, q.message
        n = base.points.reshape(-1, 3).shape[0]
        assert got["dev"][0].width * got["dev"][0].height == n == got["corrected"][0].width * got["corrected"][0].height
        assert all(m.header.stamp == q.header.stamp for m in (got["dev"][0], got["corrected"][0]))
    finally:
        tester.close()
        sp.close()


def _plain_env(domain: int) -> dict[str, str]:
    """This process's environment without any DDS / localhost variable, plus ROS_DOMAIN_ID."""
    drop = {*DDS_ENV_KEYS, LOCALHOST_ONLY_ENV, "FASTRTPS_DEFAULT_PROFILES_FILE"}
    env = {k: v for k, v in os.environ.items() if k not in drop}
    env["ROS_DOMAIN_ID"] = str(domain)
    return env


PEER = """
import sys, time, rclpy
rclpy.init()
n = rclpy.create_node("xmetro_domain0_peer")
deadline = time.monotonic() + float(sys.argv[1])
found = False
while time.monotonic() < deadline and not found:
    rclpy.spin_once(n, timeout_sec=0.2)
    found = (sys.argv[2], "/") in n.get_node_names_and_namespaces()
print("FOUND" if found else "NOT FOUND", sorted(n.get_node_names_and_namespaces()))
n.destroy_node()
rclpy.shutdown()
"""


def test_node_honours_callers_dds_environment():
    """Started with ROS_DOMAIN_ID=0 and no other ROS variable (no localhost opt-in), the node keeps that
    environment (its own log says so) and a plain peer on domain 0 sees it — safe here: the tests run in a private
    network namespace (tools/netns_run)."""
    if os.environ.get("XMETRO_IN_NETNS") != "1":
        pytest.skip("needs the private network namespace (root): a domain-0 node outside it would reach the LAN")
    env = _plain_env(0)
    with NodeProcess(base_env=env, node_name="cell3_judge") as proc:
        line = next(s for s in proc.lines if "DDS environment:" in s)
        assert "ROS_DOMAIN_ID=0" in line
        for key in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "RMW_IMPLEMENTATION", "FASTDDS_DEFAULT_PROFILES_FILE",
                    "ROS_STATIC_PEERS"):
            assert f"{key} unset" in line, line
        assert "localhost-only opt-in off" in line
        out = subprocess.run([sys.executable, "-c", PEER, str(TIMEOUT), "cell3_judge"], env=env,
                             capture_output=True, text=True, timeout=TIMEOUT + 30)
        assert out.stdout.startswith("FOUND"), out.stdout + out.stderr[-2000:]
    # the same peer on this run's private domain does not see it
    assert os.environ["ROS_DOMAIN_ID"] != "0"
    env_other = _plain_env(int(os.environ["ROS_DOMAIN_ID"]))
    with NodeProcess(base_env=env, node_name="cell3_judge") as _proc:
        out = subprocess.run([sys.executable, "-c", PEER, "5", "cell3_judge"], env=env_other,
                             capture_output=True, text=True, timeout=60)
        assert out.stdout.startswith("NOT FOUND"), out.stdout + out.stderr[-2000:]


def test_localhost_opt_in_is_applied_and_inherited():
    """With XMETRO_LOCALHOST_ONLY=1 (as make test / demo / bench set) the node applies the localhost settings."""
    env = _plain_env(int(os.environ["ROS_DOMAIN_ID"]))
    env[LOCALHOST_ONLY_ENV] = "1"
    with NodeProcess(base_env=env, node_name="xmetro_local") as proc:
        line = next(s for s in proc.lines if "DDS environment:" in s)
        assert "ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST" in line and "localhost-only opt-in on" in line, line
        assert "fastdds_localhost.xml" in line


def test_dds_env_is_changed_only_on_request(monkeypatch):
    """apply_requested_ros_env: no opt-in → the environment is left exactly as it is; the flag or the variable →
    localhost-only applied and the opt-in exported for children. pop_localhost_flag leaves ROS arguments alone."""
    from xmetro_ros.ros import dds_env

    for k in (*DDS_ENV_KEYS, LOCALHOST_ONLY_ENV):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("ROS_DOMAIN_ID", "0")
    monkeypatch.setenv("ROS_STATIC_PEERS", "192.168.1.20")
    before = dict(os.environ)
    assert dds_env.apply_requested_ros_env() is None
    assert dict(os.environ) == before
    applied = dds_env.apply_requested_ros_env(flag=True)
    assert applied is not None and os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert os.environ[LOCALHOST_ONLY_ENV] == "1" and "ROS_STATIC_PEERS" not in os.environ
    assert os.environ["ROS_DOMAIN_ID"] == "0"  # an explicit domain is kept
    argv, found = dds_env.pop_localhost_flag(["prog", "--localhost-only", "--ros-args", "-p", "a:=1"])
    assert found and argv == ["prog", "--ros-args", "-p", "a:=1"]
    argv, found = dds_env.pop_localhost_flag(["prog", "--ros-args", "--localhost-only"])
    assert not found and argv == ["prog", "--ros-args", "--localhost-only"]


TALKER = """
import sys, time, rclpy
from std_msgs.msg import String
rclpy.init()
n = rclpy.create_node("xmetro_domain0_talker")
pub = n.create_publisher(String, "/cell/chatter", 10)
end = time.monotonic() + float(sys.argv[1])
i = 0
while time.monotonic() < end:
    pub.publish(String(data=f"msg {i}"))
    i += 1
    time.sleep(0.1)
n.destroy_node()
rclpy.shutdown()
"""


@pytest.mark.timeout(180)
def test_recorder_honours_callers_dds_environment(tmp_path):
    """`xmetro record` started with only ROS_DOMAIN_ID=0 records a domain-0 talker started the same way (private
    network namespace only, as above)."""
    import signal

    if os.environ.get("XMETRO_IN_NETNS") != "1":
        pytest.skip("needs the private network namespace (root): a domain-0 participant outside it reaches the LAN")
    env = _plain_env(0)
    env["PYTHONUNBUFFERED"] = "1"
    out = tmp_path / "cell.mcap"
    rec = subprocess.Popen([sys.executable, "-m", "xmetro_ros.apps.record", "record", "/cell/chatter", "-o", str(out),
                            "--discovery-period", "0.2", "--progress", "0.2"], env=env, stdout=subprocess.PIPE,
                           stderr=subprocess.STDOUT, text=True)
    talker = subprocess.Popen([sys.executable, "-c", TALKER, "60"], env=env)
    lines: list[str] = []
    try:
        import threading

        threading.Thread(target=lambda: lines.extend(ln.rstrip("\n") for ln in rec.stdout), daemon=True).start()

        def recorded() -> int:
            prog = [ln for ln in list(lines) if ln.startswith("progress")]
            return int(prog[-1].split("/cell/chatter=")[1].split()[0]) if prog and "/cell/chatter=" in prog[-1] \
                else 0
        assert wait_for(lambda: recorded() >= 5, TIMEOUT * 2), lines[-10:]
    finally:
        talker.kill()
        talker.wait(10)
        rec.send_signal(signal.SIGINT)
        rec.wait(30)
    assert rec.returncode == 0, lines[-10:]
    line = next(ln for ln in lines if "DDS environment:" in ln)
    assert "ROS_DOMAIN_ID=0" in line and "ROS_AUTOMATIC_DISCOVERY_RANGE unset" in line, line
    assert "FASTDDS_DEFAULT_PROFILES_FILE unset" in line and "localhost-only opt-in off" in line, line
