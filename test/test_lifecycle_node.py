"""xmetro_lifecycle_node driven through its lifecycle_msgs services over DDS: configure loads the model, activate
judges scans, a scan while inactive is not processed, model changeover (deactivate → cleanup → model_dir →
configure → activate) without a new process, shutdown."""

from __future__ import annotations

import time

import pytest
from lifecycle_msgs.msg import State, Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import ReliabilityPolicy
from test_node_helpers import TIMEOUT, NodeClient, cloud_of, settings_msg, sim_scan

from xmetro_ros.msg import ScanQuality
from xmetro_ros.ros.lifecycle_node import XmetroLifecycleNode
from xmetro_ros.ros.rclpy_util import NodeSpinner, call_service, wait_for
from xmetro_ros.scan.resources import default_model_dir

S = 1_000_000_000
NAME = "xmetro_managed"


@pytest.fixture(scope="module")
def rig():
    node_sp = NodeSpinner(lambda ctx: XmetroLifecycleNode(NAME, context=ctx, parameter_overrides=[
        Parameter("min_valid_points", value=50)]))
    cli_sp = NodeSpinner(lambda ctx: Node("xmetro_lifecycle_tester", context=ctx))
    try:
        yield node_sp.node, cli_sp.node
    finally:
        cli_sp.close()
        node_sp.close()


def _state(tester: Node) -> int:
    r = call_service(tester.create_client(GetState, f"/{NAME}/get_state"), GetState.Request(), timeout=TIMEOUT)
    return int(r.current_state.id)


def _change(tester: Node, transition: int) -> bool:
    req = ChangeState.Request()
    req.transition.id = transition
    r = call_service(tester.create_client(ChangeState, f"/{NAME}/change_state"), req, timeout=TIMEOUT)
    return bool(r.success)


def _accounting(node: XmetroLifecycleNode) -> tuple[dict[str, int], int, int]:
    """The node's own record of scans: its diagnostics counters (received, judged, dropped, lost), the judged scans
    it keeps for ~/explain, and its processing queue's length."""
    assert node.diag is not None and node.core is not None
    return node.diag.counters(), len(node.core.history), len(node._queue)


def _no_quality_for(client: NodeClient, msg, seconds: float = 3.0) -> bool:
    stamp = msg.header.stamp.sec * S + msg.header.stamp.nanosec
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        client.pub_scan.publish(msg)
        time.sleep(0.3)
    return client._find("quality", stamp) is None


def test_lifecycle_transitions_drive_the_node(rig):
    node, tester = rig
    client = NodeClient(tester, target=NAME)
    assert _state(tester) == State.PRIMARY_STATE_UNCONFIGURED
    assert node.core is None and client.pub_scan.get_subscription_count() == 0

    # configure: model + scanner loaded, publishers exist, no subscription yet
    assert _change(tester, Transition.TRANSITION_CONFIGURE)
    assert _state(tester) == State.PRIMARY_STATE_INACTIVE
    assert node.core is not None and node.core.model is not None
    first_core = node.core
    base = sim_scan(10 * S)
    idle = _accounting(node)
    assert _no_quality_for(client, cloud_of(sim_scan(7 * S)))  # inactive (never activated): not processed
    assert _accounting(node) == idle, "a scan sent before activation moved the node's own accounting"

    # activate: scans are judged; the subscription follows its one (reliable) publisher (reliability: auto)
    assert _change(tester, Transition.TRANSITION_ACTIVATE)
    assert _state(tester) == State.PRIMARY_STATE_ACTIVE
    assert node.sub_scan.qos_profile.reliability == ReliabilityPolicy.RELIABLE
    client.wait_matched()
    client.pub_settings.publish(settings_msg(base, 5 * S))
    assert wait_for(lambda: node.core.settings_count >= 1, TIMEOUT)
    q, dev, _ = client.send(cloud_of(base))
    assert q.error_code == ScanQuality.ERROR_NONE and not q.settings_defaulted, q.message
    assert dev is not None and q.model_id == first_core.model_id

    # deactivate: a scan sent while inactive gets no ~/quality
    assert _change(tester, Transition.TRANSITION_DEACTIVATE)
    assert _state(tester) == State.PRIMARY_STATE_INACTIVE
    idle = _accounting(node)
    assert idle[0]["scans_received"] >= 1 and idle[1] == 1  # the scan judged while active
    assert _no_quality_for(client, cloud_of(sim_scan(20 * S)))
    assert _accounting(node) == idle, "a scan sent while inactive moved the node's own accounting"
    # load-time parameters are refused while the model is loaded
    res = node.set_parameters([Parameter("model_dir", value=str(default_model_dir()))])
    assert not res[0].successful and "clean up" in res[0].reason
    # re-activate: the scan published while inactive was never the node's to take, so it is not counted lost
    assert _change(tester, Transition.TRANSITION_ACTIVATE)
    client.wait_matched()
    q, _, _ = client.send(cloud_of(sim_scan(22 * S)))
    assert q.error_code == ScanQuality.ERROR_NONE, q.message
    assert node.diag.counters()["scans_lost"] == idle[0]["scans_lost"], node.diag.counters()
    assert _change(tester, Transition.TRANSITION_DEACTIVATE)

    # model changeover in the same process: cleanup → model_dir → configure → activate
    assert _change(tester, Transition.TRANSITION_CLEANUP)
    assert _state(tester) == State.PRIMARY_STATE_UNCONFIGURED and node.core is None
    res = node.set_parameters([Parameter("model_dir", value=str(default_model_dir()))])
    assert res[0].successful, res[0].reason
    assert _change(tester, Transition.TRANSITION_CONFIGURE)
    assert node.core is not first_core and node.core.values["model_dir"] == str(default_model_dir())
    assert _change(tester, Transition.TRANSITION_ACTIVATE)
    client.wait_matched()
    base2 = sim_scan(30 * S)
    client.pub_settings.publish(settings_msg(base2, 25 * S))
    assert wait_for(lambda: node.core.settings_count >= 1, TIMEOUT)
    q2, dev2, _ = client.send(cloud_of(base2))
    assert q2.error_code == ScanQuality.ERROR_NONE and dev2 is not None, q2.message

    # shutdown from active: finalized, everything released
    assert _change(tester, Transition.TRANSITION_ACTIVE_SHUTDOWN)
    assert _state(tester) == State.PRIMARY_STATE_FINALIZED
    assert node.core is None
    assert wait_for(lambda: client.pub_scan.get_subscription_count() == 0, TIMEOUT)


def test_configure_fails_cleanly_on_a_bad_parameter():
    sp = NodeSpinner(lambda ctx: XmetroLifecycleNode("xmetro_bad_cfg", context=ctx, parameter_overrides=[
        Parameter("cloud_overflow", value="explode")]))
    try:
        node = sp.node
        assert node.trigger_configure() == TransitionCallbackReturn.FAILURE  # → back to unconfigured
        assert node.core is None
        # fix the parameter (settable while unconfigured) and configure again
        assert node.set_parameters([Parameter("cloud_overflow", value="decimate")])[0].successful
        assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
        assert node.core is not None and node.core.values["cloud_overflow"] == "decimate"
    finally:
        sp.close()
