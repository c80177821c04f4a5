"""The scan subscription fits its publishers (``reliability: auto``, rosbag2's recorder rule), and scans lost in
transport are said on /diagnostics with their fix — never lost without a word.

Measured before (a user's default Fast DDS settings, no profile file, the node's best-effort subscription): an 856 kB
cloud from a reliable publisher never reached the node in 12 tries, while 276 kB clouds did.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2

from xmetro_ros.ros.diagnostics import DiagnosticsState, lost_scans_reason
from xmetro_ros.ros.node import XmetroNode, reliability_for_publishers
from xmetro_ros.ros.rclpy_util import NodeProcess, NodeSpinner, wait_for

HERE = Path(__file__).resolve().parent
TIMEOUT = 30.0


def test_reliability_for_publishers_is_rosbag2s_rule():
    assert reliability_for_publishers([]) == "best_effort"
    assert reliability_for_publishers(["reliable"]) == "reliable"
    assert reliability_for_publishers(["reliable", "reliable"]) == "reliable"
    assert reliability_for_publishers(["reliable", "best_effort"]) == "best_effort"
    assert reliability_for_publishers(["best_effort"]) == "best_effort"


def test_a_loss_warns_with_its_fix_for_a_while():
    d = DiagnosticsState("judge", "scanner", "model")
    d.on_settings()
    d.on_received()
    d.last_verdict, d.last_message = 0, "scan OK"
    assert d.level() == 0
    d.on_lost(1, dds_event=True)
    arr = d.build(None)
    assert d.level() == 1 and "lost in transport" in arr.status[0].message
    assert "config/fastdds_localhost.xml" in arr.status[0].message  # the fix for a best-effort subscription
    d.scan_reliability = "reliable"
    assert "queue" in lost_scans_reason(3, 0, "reliable")
    d._last_loss = time.monotonic() - 61.0  # the warning holds LOSS_HOLD_S, then the level follows the scans again
    assert d.level() == 0


def test_a_loss_shows_behind_a_worse_reason():
    """A best-effort subscription that lost most scans and judged the one that got through on default settings:
    ERROR for the settings, and the message goes on to the loss and its fix (what CI once saw: the loss hidden)."""
    d = DiagnosticsState("judge", "scanner", "model")
    d.on_received()
    d.last_verdict, d.last_message = 1, "settings defaulted"
    d.on_lost(5, dds_event=True)
    msg = d.build(None).status[0].message
    assert d.level() == 2
    assert msg.index("no ScannerSettings ever arrived") < msg.index("lost in transport")
    assert "config/fastdds_localhost.xml" in msg


def _rel(sub) -> ReliabilityPolicy:
    return sub.qos_profile.reliability


def test_auto_follows_the_publishers_and_overrides_win():
    """Default parameters: best effort with no publisher, reliable once every publisher is reliable, best effort
    again when a best-effort publisher joins (which a reliable reader would never match); a fixed ``reliability``
    or a ``qos_overrides`` parameter is left alone."""
    auto = NodeSpinner(lambda ctx: XmetroNode(context=ctx, cli_args=["--ros-args", "-r", "__ns:=/qa"]))
    fixed = NodeSpinner(lambda ctx: XmetroNode(context=ctx, cli_args=["--ros-args", "-r", "__ns:=/qf"],
                                               parameter_overrides=[Parameter("reliability", value="best_effort")]))
    ovr = NodeSpinner(lambda ctx: XmetroNode(context=ctx, cli_args=["--ros-args", "-r", "__ns:=/qo"],
                                             parameter_overrides=[Parameter(
                                                 "qos_overrides./qo/scan.subscription.reliability",
                                                 value="best_effort")]))
    tester = NodeSpinner(lambda ctx: Node("xmetro_qos_tester", context=ctx))
    try:
        assert _rel(auto.node.sub_scan) == ReliabilityPolicy.BEST_EFFORT  # nobody publishes yet
        reliable = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
        pubs = {ns: tester.node.create_publisher(PointCloud2, f"/{ns}/scan", reliable) for ns in ("qa", "qf", "qo")}
        assert wait_for(lambda: _rel(auto.node.sub_scan) == ReliabilityPolicy.RELIABLE, TIMEOUT)
        assert wait_for(lambda: pubs["qa"].get_subscription_count() == 1, TIMEOUT)
        assert auto.node.diag.scan_reliability == "reliable"
        be = tester.node.create_publisher(PointCloud2, "/qa/scan", QoSProfile(
            depth=5, reliability=ReliabilityPolicy.BEST_EFFORT))
        assert wait_for(lambda: _rel(auto.node.sub_scan) == ReliabilityPolicy.BEST_EFFORT, TIMEOUT)
        assert wait_for(lambda: be.get_subscription_count() == 1 and pubs["qa"].get_subscription_count() == 1,
                        TIMEOUT)
        time.sleep(3.0)
        for sp in (fixed, ovr):
            assert _rel(sp.node.sub_scan) == ReliabilityPolicy.BEST_EFFORT
    finally:
        for sp in (tester, ovr, fixed, auto):
            sp.close()


def _default_dds_env(domain: int) -> dict[str, str]:
    """The environment of a user who set nothing: Fast DDS's default transports, no profile file, default discovery
    range (the test session runs in a private network namespace, so nothing leaves this machine)."""
    env = {k: v for k, v in os.environ.items() if k not in (
        "FASTDDS_DEFAULT_PROFILES_FILE", "FASTRTPS_DEFAULT_PROFILES_FILE", "ROS_AUTOMATIC_DISCOVERY_RANGE",
        "ROS_STATIC_PEERS", "XMETRO_LOCALHOST_ONLY", "FASTDDS_BUILTIN_TRANSPORTS")}
    env["ROS_DOMAIN_ID"] = str(domain)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(HERE), env.get("PYTHONPATH")]))
    return env


def _drive(env: dict[str, str], topic: str, reliability: str, n_bytes: int = 856_000, count: int = 6,
           listen: float = 4.0) -> dict:
    out = subprocess.run([sys.executable, str(HERE / "big_cloud_peer.py"), "--topic", topic,
                          "--reliability", reliability, "--bytes", str(n_bytes), "--count", str(count),
                          "--listen", str(listen)], env=env, capture_output=True, text=True, timeout=240)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.timeout(420)
@pytest.mark.skipif(os.environ.get("XMETRO_IN_NETNS") != "1", reason="default DDS discovery must stay in a private "
                    "network namespace (run as root: the conftest re-executes in one)")
def test_large_clouds_on_default_dds_settings_arrive_or_are_reported():
    """Both processes on a user's default DDS settings, 856 kB clouds from a reliable driver: with the default
    ``reliability: auto`` they are received; with a fixed best-effort subscription they are lost in transport, and
    /diagnostics says so at WARN with the fix (not OK, not silent)."""
    domain = 150 + os.getpid() % 50
    env = _default_dds_env(domain)
    with NodeProcess(base_env=env, node_name="judge_auto").start(timeout=90) as auto:
        got = _drive(env, "/scan", "reliable")
        # issue 24: a 25 MB organized-size cloud from a reliable publisher, default parameters, default DDS
        # (measured: received and judged, about 7 s each on this 2-core machine, most of it the judging)
        big = _drive(env, "/scan", "reliable", n_bytes=25_000_000, count=2, listen=25.0)
    assert got["matched"], got
    assert int(got["status"]["scans_received"]) >= 5, got
    assert "lost in transport" not in got["message"], got
    assert int(big["status"]["scans_received"]) - int(got["status"]["scans_received"]) == 2, big
    assert int(big["status"]["scans_judged"]) == int(big["status"]["scans_received"]), big
    assert big["status"]["scans_lost"] == "0" and big["status"]["dds_message_lost_events"] == "0", big
    assert any("scan subscription now reliable" in ln for ln in auto.lines), auto.lines[-20:]

    with NodeProcess(base_env=env, node_name="judge_be", params={"reliability": "best_effort"}).start(timeout=90):
        lost = _drive(env, "/scan", "reliable")
    assert lost["matched"], lost
    # the transport lost them, the measured failure: all 6 on an idle machine; once in CI a sample got through
    assert int(lost["status"]["scans_received"]) <= 2, lost
    assert int(lost["status"]["dds_message_lost_events"]) + int(lost["status"]["scans_lost"]) > 0, lost
    assert lost["level"] >= 1 and "lost in transport" in lost["message"], lost
    assert "config/fastdds_localhost.xml" in lost["message"], lost
