"""``xmetro_lifecycle_node``: the node as a ROS 2 managed (lifecycle) node — same topics, services and parameters
as ``xmetro_node`` (node.py), driven by ``lifecycle_msgs`` services (``~/change_state``, ``~/get_state``, ...).

Transitions (the wiring is node.py's :class:`XmetroWiring`, shared, not copied):

- **configure**: read the parameters, load the model set and the scanner (XmetroCore), create the publishers
  (lifecycle publishers: they publish only while active). Fails (back to unconfigured) when the parameters are
  invalid; a model that cannot be loaded configures DEGRADED, as the plain node starts.
- **activate**: create the subscriptions (``scan``, ``scanner_settings``), the services, the worker thread and the
  /diagnostics timer; scans are judged from now on.
- **deactivate**: destroy the subscriptions, services and timer, stop the worker and drop queued scans: nothing
  is processed while inactive. The model stays loaded (re-activate resumes at once).
- **cleanup**: release the publishers and the model (back to unconfigured). Load-time parameters (``model_dir``,
  ``inference_threads``, ``reliability``, ...) can be set only while unconfigured: a model changeover without
  restarting the process is deactivate → cleanup → set ``model_dir`` → configure → activate.
- **shutdown**: release everything from any state.
"""

from __future__ import annotations

from typing import Any

from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn

from . import params as node_params
from .node import XmetroWiring, run_node

__all__ = ["XmetroLifecycleNode", "main"]


class XmetroLifecycleNode(XmetroWiring, LifecycleNode):
    """Managed variant of ``XmetroNode`` (see the module docstring). Starts unconfigured."""

    def __init__(self, node_name: str = "xmetro_node", **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self._init_wiring(writable=tuple(node_params.LOAD_TIME))
        self.get_logger().info("xmetro lifecycle node unconfigured: configure loads the model, activate starts")

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self._load_core()
        except Exception as e:
            self.get_logger().error(f"configure failed: {type(e).__name__}: {e}")
            self.core = self.diag = None
            return TransitionCallbackReturn.FAILURE
        self._create_outputs(self.create_lifecycle_publisher)
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        ret = super().on_activate(state)  # activates the lifecycle publishers
        if ret != TransitionCallbackReturn.SUCCESS:
            return ret
        self._create_inputs()
        self._log_ready()
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._destroy_inputs()
        self.get_logger().info("deactivated: scans are no longer taken")
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._destroy_inputs()
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._destroy_inputs()
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def _release(self) -> None:
        for pub in self._outputs:
            self.destroy_lifecycle_publisher(pub)
        self._outputs = []
        self.core = None
        self.diag = None

    def destroy_node(self) -> None:
        self._destroy_wiring()  # destroyed while active: the inputs are still there
        super().destroy_node()
        # rclpy's LifecycleNode leaves its state machine, which holds the node's handle: without this the node and
        # its DDS participant stay until the garbage collector runs (test_node_teardown.py).
        state_machine = getattr(self, "_state_machine", None)
        if state_machine is not None:
            state_machine.destroy_when_not_in_use()


def main(args: list[str] | None = None) -> int:
    """Console script ``xmetro_lifecycle_node [--localhost-only] --ros-args ...`` (starts unconfigured; drive it
    with ``ros2 lifecycle set <node> configure`` / ``activate`` or a launch file's lifecycle events)."""
    return run_node(XmetroLifecycleNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
