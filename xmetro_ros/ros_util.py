"""Small rclpy helpers shared by the node, the tools, the tests and the benchmarks.

- :class:`NodeSpinner`: spin one node in a background thread on its own context and executor.
- :func:`call_service`: call a service from a thread other than the spinning one, with retries.
- :func:`wait_for`: poll a condition with a timeout.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor

from .ros_env import apply_ros_env

__all__ = ["NodeSpinner", "call_service", "wait_for", "ServiceTimeoutError", "new_context"]


class ServiceTimeoutError(TimeoutError):
    """A service was not available or did not answer in time."""


def new_context(args: list[str] | None = None) -> Context:
    """A fresh, initialised rclpy context with the localhost-only environment applied."""
    apply_ros_env()
    ctx = Context()
    rclpy.init(args=args, context=ctx)
    return ctx


class NodeSpinner:
    """Create a node with ``factory(context)`` and spin it in a daemon thread; ``close()`` shuts all down.

    Usable as a context manager. ``node`` is the created node; ``context`` its private context.
    """

    def __init__(self, factory: Callable[[Context], Any]) -> None:
        self.context = new_context()
        try:
            self.node = factory(self.context)
        except Exception:
            self.context.try_shutdown()
            raise
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, name=f"spin-{self.node.get_name()}", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except Exception:  # context shut down while spinning
            pass

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=5.0)
        try:
            self.node.destroy_node()
        except Exception:
            pass
        self.context.try_shutdown()
        self._thread.join(timeout=5.0)

    def __enter__(self) -> NodeSpinner:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def wait_for(cond: Callable[[], bool], timeout: float = 30.0, period: float = 0.02) -> bool:
    """Poll ``cond`` until it is true or ``timeout`` seconds pass; return its last value."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(period)
    return bool(cond())


def call_service(client: Any, request: Any, timeout: float = 60.0, attempt_timeout: float = 10.0) -> Any:
    """Call a service from a client whose node spins in another thread; return the response.

    DDS discovery is asynchronous: ``wait_for_service`` only says the request reader is matched; the server's
    response writer may not have matched this client's reader yet, and Fast DDS then drops the response ("failed to
    send response"). So the call is retried (requests must be idempotent), each attempt waiting twice as long as the
    previous one (first ``attempt_timeout``), until ``timeout`` seconds have passed.

    Raises:
        ServiceTimeoutError: not available, or no answer within ``timeout`` seconds.
    """
    deadline = time.monotonic() + timeout
    if not client.wait_for_service(timeout_sec=timeout):
        raise ServiceTimeoutError(f"service {client.srv_name} not available within {timeout:g} s")
    while True:
        done = threading.Event()
        future = client.call_async(request)
        future.add_done_callback(lambda _f: done.set())
        remaining = deadline - time.monotonic()
        waited = done.wait(max(0.1, min(attempt_timeout, remaining)))
        attempt_timeout *= 2
        if waited:
            exc = future.exception()
            if exc is not None:
                raise exc
            return future.result()
        client.remove_pending_request(future)
        if time.monotonic() >= deadline:
            raise ServiceTimeoutError(f"service {client.srv_name} did not answer within {timeout:g} s")
