"""In-line reference monitoring through a real node over DDS (issue 17): scans of a certified sphere published on
``reference_scan`` are judged, checked against the sphere and tracked by the drift monitor; ``~/reference``
(ReferenceCheck) and ``/diagnostics`` report it.

Truth from the simulator (test_reference_check.py measures the rates over many resampled streams): a stable stream
of 24 reference scans stays OK; a stream whose laser line starts to tilt (2 µm of range error per mm along the line)
after 12 reference scans raises WARN within 3 reference scans, names the line position (or x, the same variable
when the head looks down) as the candidate effect, and turns /diagnostics WARN; ``~/reset_reference`` starts a new
in-control level; a scan of another sphere is a MISMATCH and does not feed the monitor."""

from __future__ import annotations

import numpy as np
import pytest
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from ros_harness import Inbox
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger
from test_node_helpers import TIMEOUT, NodeClient, settings_msg
from test_reference_check import CENTER, RADIUS, SETTINGS, SWITCH, TILT, reference_scan

from xmetro_ros.msg import ReferenceCheck
from xmetro_ros.ros.convert import scan_to_cloud
from xmetro_ros.ros.node import XmetroNode
from xmetro_ros.ros.rclpy_util import NodeSpinner, call_service, wait_for
from xmetro_ros.scan.artifacts import Sphere
from xmetro_ros.sim import simulate_scan

S = 1_000_000_000
STREAM = 24
MAX_DELAY = 3
WARN_LEVEL = 1


@pytest.fixture(scope="module")
def rig():
    overrides = [Parameter("reference_radius", value=RADIUS * 1e-3),
                 Parameter("reference_center", value=[c * 1e-3 for c in CENTER]),
                 Parameter("reference_warmup", value=10), Parameter("reliability", value="reliable"),
                 Parameter("min_valid_points", value=50), Parameter("queue_depth", value=8)]
    node_sp = NodeSpinner(lambda ctx: XmetroNode(context=ctx, parameter_overrides=overrides))
    cli_sp = NodeSpinner(lambda ctx: __import__("rclpy.node", fromlist=["Node"]).Node("xmetro_ref_tester",
                                                                                      context=ctx))
    client = NodeClient(cli_sp.node)
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.VOLATILE)
    pub_ref = cli_sp.node.create_publisher(PointCloud2, "reference_scan", qos)
    inbox = Inbox(cli_sp.node, ReferenceCheck, "/xmetro_node/reference",
                  QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.VOLATILE))
    reset = cli_sp.node.create_client(Trigger, "/xmetro_node/reset_reference")
    try:
        client.wait_matched(node_sp.node)
        assert wait_for(lambda: pub_ref.get_subscription_count() > 0 and inbox.sub.get_publisher_count() > 0,
                        TIMEOUT)
        # one settings message for every scan of the test (stamped before all of them, transient-local)
        client.pub_settings.publish(settings_msg(reference_scan(0), 1 * S, frame_id="artifact"))
        assert wait_for(lambda: node_sp.node.core.settings_for(10 * S) is not None, TIMEOUT)
        yield node_sp.node, client, pub_ref, inbox, reset
    finally:
        cli_sp.close()
        node_sp.close()


def _send(pub_ref, inbox: Inbox, scan, stamp_ns: int) -> ReferenceCheck:
    pub_ref.publish(scan_to_cloud(scan, header_stamp=stamp_ns))
    return inbox.wait(lambda m: m.header.stamp.sec * S + m.header.stamp.nanosec == stamp_ns, timeout=TIMEOUT)


def test_stable_stream_stays_ok_then_a_tilt_raises_warn_with_its_candidate(rig):
    _node, client, pub_ref, inbox, reset = rig
    stable = [_send(pub_ref, inbox, reference_scan(1000 + k), (100 + k) * S) for k in range(STREAM)]
    assert [m.state for m in stable[:9]] == [ReferenceCheck.STATE_WARMUP] * 9
    assert all(m.state == ReferenceCheck.STATE_OK for m in stable[9:]), [m.message for m in stable]
    assert stable[-1].reference_scans == STREAM and stable[-1].points > 1000
    assert 0.92 < stable[-1].coverage < 0.99 and abs(stable[-1].residual_mean) < 2e-6  # metres
    # the reference scans were judged like any scan (their ScanQuality is published too)
    assert client._find("quality", 100 * S) is not None

    assert call_service(reset, Trigger.Request()).success
    mark = client.diag_mark()
    stream = []
    for k in range(SWITCH + MAX_DELAY + 1):
        tilt = TILT if k >= SWITCH else 0.0
        stream.append(_send(pub_ref, inbox, reference_scan(2000 + k, tilt), (200 + k) * S))
    states = [m.state for m in stream]
    assert ReferenceCheck.STATE_WARN not in states[:SWITCH], [m.message for m in stream[:SWITCH]]
    first = next(i for i, s in enumerate(states) if s == ReferenceCheck.STATE_WARN)
    assert 1 <= first + 1 - SWITCH <= MAX_DELAY
    warn = stream[first]
    assert warn.first_warn_scan == first + 1 and warn.statistic and warn.detector and warn.value > warn.threshold
    assert warn.candidate_effect in ("u", "x") and warn.candidate_p < 1e-6, warn.message
    assert all(s == ReferenceCheck.STATE_WARN for s in states[first:])  # held until reset
    d = client.wait_diag_level(WARN_LEVEL, mark, lambda st: "reference drift" in st.message)
    values = {kv.key: kv.value for kv in d.status[0].values}
    assert values["reference_state"] == "WARN" and "candidate effect" in values["reference_message"]

    # a scan of another sphere: MISMATCH, the monitor's count does not move
    other = simulate_scan(Sphere(20.0, CENTER), SETTINGS, seed=5)
    m = _send(pub_ref, inbox, other, 300 * S)
    assert m.state == ReferenceCheck.STATE_MISMATCH and m.reference_scans == warn.reference_scans + (
        len(stream) - 1 - first) and "does not show the sphere" in m.message
    # reset: the monitor learns a new in-control level
    assert call_service(reset, Trigger.Request()).success
    m = _send(pub_ref, inbox, reference_scan(3000), 400 * S)
    assert m.state == ReferenceCheck.STATE_WARMUP and m.reference_scans == 1
    assert np.isfinite(m.residual_rms) and m.residual_rms < 30e-6


def test_scans_on_the_scan_topic_are_not_reference_scans(rig):
    _node, client, _pub, inbox, _reset = rig
    n = len(inbox.messages)
    q, dev, _ = client.send(scan_to_cloud(reference_scan(4000), header_stamp=500 * S))
    assert q.error_code == 0 and dev is not None
    assert not wait_for(lambda: len(inbox.messages) > n, 1.0)
