"""A destroyed xmetro node leaves the ROS graph when it is destroyed, not when Python's garbage collector happens to
run: ``destroy_node`` also destroys its action server (``~/recommend_settings``), which holds the node's handle.

Before this, a closed node and its DDS participant lived on until a collection broke the cycle. A process that makes
and closes nodes (a component container, this test suite) then piled up participants; past 32 on one host,
rmw_fastrtps' localhost discovery (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``) no longer reaches new ones, and a
client waited in vain for a service. The collector is off during each test so that it cannot hide a leak.
"""

from __future__ import annotations

import gc
from collections.abc import Iterator

import pytest
from rclpy.action import ActionServer

from xmetro_ros.ros.rclpy_util import NodeSpinner, wait_for

TIMEOUT = 30.0


@pytest.fixture
def no_collector() -> Iterator[None]:
    gc.collect()
    gc.disable()
    try:
        yield
    finally:
        gc.enable()


def _names(observer) -> set[str]:
    return {name for name, _ in observer.get_node_names_and_namespaces()}


@pytest.mark.parametrize("kind", ["node", "lifecycle_active"])
def test_a_destroyed_node_leaves_the_graph_without_the_garbage_collector(kind: str, no_collector: None) -> None:
    from rclpy.node import Node

    from xmetro_ros.ros.lifecycle_node import XmetroLifecycleNode
    from xmetro_ros.ros.node import XmetroNode

    name = f"xmetro_teardown_{kind}"

    def make(ctx):
        if kind == "node":
            return XmetroNode(name, context=ctx)
        node = XmetroLifecycleNode(name, context=ctx)
        node.trigger_configure()
        node.trigger_activate()  # active: its inputs, the action server among them, exist
        return node

    with NodeSpinner(lambda ctx: Node("xmetro_teardown_observer", context=ctx)) as observer:
        sp = NodeSpinner(make)
        try:
            assert any(isinstance(e, ActionServer) for e in sp.node._inputs)
            assert wait_for(lambda: name in _names(observer.node), TIMEOUT), "the node never appeared"
        finally:
            sp.close()
        assert wait_for(lambda: name not in _names(observer.node), TIMEOUT), \
            f"{name} is still in the ROS graph after destroy_node (something still holds its handle)"


def test_a_service_not_found_names_what_the_client_sees() -> None:
    """The not-available error of ``call_service`` says what the client's node sees: the live node, and no server
    of the service it waited for, so a CI failure tells "nothing discovered" from "server seen, not matched"."""
    from rclpy.node import Node

    from xmetro_ros.ros.rclpy_util import ServiceTimeoutError, call_service
    from xmetro_ros.srv import Explain

    with NodeSpinner(lambda ctx: Node("xmetro_teardown_peer", context=ctx)), \
            NodeSpinner(lambda ctx: Node("xmetro_teardown_client", context=ctx)) as cl:
        assert wait_for(lambda: "xmetro_teardown_peer" in _names(cl.node), TIMEOUT)
        client = cl.node.create_client(Explain, "/xmetro_teardown_gone/explain")
        with pytest.raises(ServiceTimeoutError) as err:
            call_service(client, Explain.Request(), timeout=0.5, node=cl.node)
    msg = str(err.value)
    assert "sees nodes [/xmetro_teardown_peer]" in msg and "0 server(s) of /xmetro_teardown_gone/explain" in msg, msg
