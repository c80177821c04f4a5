"""``~/recommend_settings`` as a ROS 2 action over DDS: same best candidate as the service, feedback after each
orientation, a cancel stops the search (CANCELED, before the end of the grid)."""

from __future__ import annotations

import itertools
import threading

import pytest
from action_msgs.msg import GoalStatus
from rclpy.action import ActionClient
from rclpy.node import Node
from rclpy.parameter import Parameter
from test_node_helpers import TIMEOUT, NodeClient, cloud_of, settings_msg, sim_scan

from xmetro_ros.action import RecommendSettings as RecommendAction
from xmetro_ros.msg import ScanQuality
from xmetro_ros.ros.rclpy_util import NodeSpinner, call_service, wait_for
from xmetro_ros.srv import RecommendSettings

S = 1_000_000_000
NAME = "xmetro_node"


@pytest.fixture(scope="module")
def rig():
    node_sp = NodeSpinner(lambda ctx: __import__("xmetro_ros.ros.node", fromlist=["XmetroNode"]).XmetroNode(
        context=ctx, parameter_overrides=[Parameter("min_valid_points", value=50),
                                          Parameter("recommend_max_points", value=300)]), threads=3)
    cli_sp = NodeSpinner(lambda ctx: Node("xmetro_action_tester", context=ctx))
    client = NodeClient(cli_sp.node)
    try:
        client.wait_matched(node_sp.node)
        base = sim_scan(10 * S)
        client.pub_settings.publish(settings_msg(base, 5 * S))
        assert wait_for(lambda: node_sp.node.core.settings_count >= 1, TIMEOUT)
        q, _, _ = client.send(cloud_of(base))
        assert q.error_code == ScanQuality.ERROR_NONE, q.message
        yield node_sp.node, cli_sp.node, q
    finally:
        cli_sp.close()
        node_sp.close()


def _goal(q: ScanQuality, **kw) -> RecommendAction.Goal:
    g = RecommendAction.Goal(scan_stamp=q.header.stamp, region_radius=0.0, **kw)
    return g


def _run_goal(client_node: Node, ac: ActionClient, goal, cancel_after: int | None = None):
    """Send ``goal`` from ``ac`` (of ``client_node``, spun by a single-threaded executor in another thread); return
    (status, result, feedbacks). ``cancel_after``: request a cancel after that many feedback messages."""
    feedback: list = []
    done = threading.Event()
    out: dict = {}

    def on_feedback(msg) -> None:
        feedback.append(msg.feedback)
        if cancel_after is not None and len(feedback) == cancel_after and "handle" in out:
            out["handle"].cancel_goal_async()

    def on_result(fut) -> None:
        r = fut.result()
        out["status"], out["result"] = r.status, r.result
        done.set()

    def on_accept(fut) -> None:
        h = fut.result()
        out["handle"] = h
        if not h.accepted:
            done.set()
            return
        h.get_result_async().add_done_callback(on_result)

    assert ac.wait_for_server(timeout_sec=TIMEOUT)

    def send() -> None:
        ac.send_goal_async(goal, feedback_callback=on_feedback).add_done_callback(on_accept)

    # Sent from the client node's own (single-threaded) executor, not this thread: rclpy 9.1.2's send_goal_async
    # registers the goal's future under its lock, then registers a second one and returns that. When the spinning
    # thread takes the server's acceptance in between, it completes the first and the returned future never
    # completes (CI on a loaded machine: all three tests here waited 120 s for a result, the server having logged
    # nothing wrong). On the executor's thread the acceptance cannot be taken before send_goal_async returns.
    executor = client_node.executor
    assert executor is not None
    executor.create_task(send)
    assert done.wait(TIMEOUT * 4), "no action result"
    return out.get("status"), out.get("result"), feedback


def test_action_matches_service_and_sends_feedback(rig):
    _node, tester, q = rig
    req = RecommendSettings.Request(scan_stamp=q.header.stamp, region_radius=0.0)
    srv = call_service(tester.create_client(RecommendSettings, f"/{NAME}/recommend_settings"), req,
                       timeout=TIMEOUT * 4)
    assert srv.success, srv.message
    ac = ActionClient(tester, RecommendAction, f"/{NAME}/recommend_settings")
    status, res, fb = _run_goal(tester, ac, _goal(q))
    assert status == GoalStatus.STATUS_SUCCEEDED, res.message
    assert res.success
    # the same search, the same best candidate
    assert res.recommended_settings == srv.recommended_settings
    assert res.recommended_orientation == srv.recommended_orientation
    assert res.p95_abs_error_after == srv.p95_abs_error_after
    assert res.mean_abs_error_before == srv.mean_abs_error_before
    assert list(res.alternatives) == list(srv.alternatives)
    # feedback: one per orientation, counts rising to the grid size, best p95 falling to the answer's
    assert fb, "no feedback"
    total = fb[-1].orientations_total
    assert total >= 2
    assert [f.orientations_evaluated for f in fb] == list(range(1, total + 1))
    assert fb[-1].best_p95_abs_error == pytest.approx(res.p95_abs_error_after, rel=1e-12)
    bests = [f.best_p95_abs_error for f in fb]
    # the running best falls over the search; when the answer keeps the current set-up (its predicted gain inside
    # its uncertainty) the last report is the kept set-up's figure, which may be above the search's best
    # (with the search ensemble the feedback counts the members' orientations one after another, the running best
    # being the lowest any member has predicted, and the last report is the ensemble's answer, which is a mean)
    kept = "keep the current set-up" in res.message or "search ensemble" in res.message
    assert all(b2 <= b1 for b1, b2 in itertools.pairwise(bests[:-1] if kept else bests)), (bests, res.message)


def test_action_cancel_stops_the_search(rig):
    node, tester, q = rig
    # A long search (343 orientations, every one kept and predicted) so that the cancel comes before its end.
    node.set_parameters([Parameter("recommend_tilt_steps", value=7), Parameter("recommend_turn_steps", value=7),
                         Parameter("recommend_min_coverage", value=0.0), Parameter("recommend_max_points", value=1000),
                         Parameter("recommend_max_seconds", value=600.0)])
    try:
        ac = ActionClient(tester, RecommendAction, f"/{NAME}/recommend_settings")
        status, res, fb = _run_goal(tester, ac, _goal(q), cancel_after=1)
        assert status == GoalStatus.STATUS_CANCELED, (status, res.message)
        assert not res.success and "cancelled after" in res.message
        total = fb[0].orientations_total
        ens = node.core.search_ensemble
        assert total == 7 * 7 * 7 * (1 if ens is None else len(ens.members))
        assert fb[-1].orientations_evaluated < total  # stopped before the end of the grid
    finally:
        node.set_parameters([Parameter("recommend_tilt_steps", value=3), Parameter("recommend_turn_steps", value=3),
                             Parameter("recommend_min_coverage", value=0.95),
                             Parameter("recommend_max_points", value=300),
                             Parameter("recommend_max_seconds", value=10.0)])


def test_action_refused_request_aborts(rig):
    _node, tester, _q = rig
    ac = ActionClient(tester, RecommendAction, f"/{NAME}/recommend_settings")
    g = RecommendAction.Goal()
    g.scan_stamp.sec = 12345  # no such judged scan
    status, res, _fb = _run_goal(tester, ac, g)
    assert status == GoalStatus.STATUS_ABORTED and not res.success and res.message
