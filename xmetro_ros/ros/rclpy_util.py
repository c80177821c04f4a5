"""Small rclpy helpers shared by the node, the tools, the tests and the benchmarks.

- :class:`NodeSpinner`: spin one node in a background thread on its own context and executor.
- :func:`call_service`: call a service from a thread other than the spinning one, with retries.
- :func:`wait_for`: poll a condition with a timeout.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import rclpy
from rclpy.context import Context
from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor

from .dds_env import apply_requested_ros_env, ros_env

__all__ = ["READY_MESSAGE", "NodeMixin", "NodeProcess", "NodeSpinner", "SequenceGaps", "ServiceTimeoutError",
           "call_service", "graph_seen_by", "new_context", "other_nodes", "wait_for"]

# The line xmetro_node logs once it is up (ros/node.py); NodeProcess waits for it.
READY_MESSAGE = "xmetro_node ready"

# Base of the mixins that make up xmetro_node's wiring (mixed into rclpy Node subclasses, plain and lifecycle):
# type-checked as a Node, nothing at run time.
if TYPE_CHECKING:
    from rclpy.node import Node as NodeMixin
else:
    NodeMixin = object


class ServiceTimeoutError(TimeoutError):
    """A service was not available or did not answer in time."""


def new_context(args: list[str] | None = None) -> Context:
    """A fresh, initialised rclpy context; the localhost-only environment is applied when opted in
    (``XMETRO_LOCALHOST_ONLY=1``, as the tests, demo and benchmarks set), else the caller's DDS environment holds."""
    apply_requested_ros_env()
    ctx = Context()
    rclpy.init(args=args, context=ctx)
    return ctx


class NodeSpinner:
    """Create a node with ``factory(context)`` and spin it in a daemon thread; ``close()`` shuts all down.

    Usable as a context manager. ``node`` is the created node; ``context`` its private context. ``threads`` > 1
    spins it on a MultiThreadedExecutor (as ``xmetro_node`` does: an action's cancel is then served while its goal
    executes).
    """

    def __init__(self, factory: Callable[[Context], Any], threads: int = 1) -> None:
        self.context = new_context()
        try:
            self.node = factory(self.context)
        except Exception:
            self.context.try_shutdown()
            raise
        self.executor = (SingleThreadedExecutor(context=self.context) if threads <= 1
                         else MultiThreadedExecutor(num_threads=threads, context=self.context))
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


def call_service(client: Any, request: Any, timeout: float = 60.0, attempt_timeout: float = 10.0,
                 node: Any = None) -> Any:
    """Call a service from a client whose node spins in another thread; return the response.

    DDS discovery is asynchronous: ``wait_for_service`` only says the request reader is matched; the server's
    response writer may not have matched this client's reader yet, and Fast DDS then drops the response ("failed to
    send response"). So the call is retried (requests must be idempotent), each attempt waiting twice as long as the
    previous one (first ``attempt_timeout``), until ``timeout`` seconds have passed.

    ``node``, the client's node, only adds to the not-available error what that node sees of the graph (the other
    nodes, the servers of the service), which tells "nothing discovered" from "server seen, endpoints not matched".

    Raises:
        ServiceTimeoutError: not available, or no answer within ``timeout`` seconds.
    """
    deadline = time.monotonic() + timeout
    if not client.wait_for_service(timeout_sec=timeout):
        seen = "" if node is None else f"; {graph_seen_by(node, client.srv_name)}"
        raise ServiceTimeoutError(f"service {client.srv_name} not available within {timeout:g} s{seen}")
    while True:
        done = threading.Event()
        future = client.call_async(request)
        future.add_done_callback(lambda _f, done=done: done.set())
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


def other_nodes(node: Any) -> list[str]:
    """The full names of the nodes ``node`` sees in the graph, itself left out, sorted."""
    return sorted(f"{ns.rstrip('/')}/{n}" for n, ns in node.get_node_names_and_namespaces() if n != node.get_name())


def graph_seen_by(node: Any, service: str) -> str:
    """One line: the other nodes ``node`` sees and how many servers of ``service`` it sees."""
    servers = node.count_services(service)
    return f"{node.get_name()} sees nodes [{', '.join(other_nodes(node))}] and {servers} server(s) of {service}"


class NodeProcess:
    """Run ``xmetro_node`` as a child process (``python -m xmetro_ros.ros.node``) with the localhost ROS environment.

    ``start()`` launches it and waits for its ready log line (``READY_MESSAGE``); ``stop()`` sends SIGINT and
    waits (SIGKILL after ``stop_timeout``). Its combined stdout/stderr lines are kept in ``lines``. Usable as a
    context manager.

    Args:
        params_file: a ROS params file (e.g. config/xmetro.yaml) or None.
        params: parameter overrides {name: value} (``-p name:=value``).
        domain_id: ROS_DOMAIN_ID for the child (None: this process's, else a fresh one).
        node_name: remaps the node name (``-r __node:=NAME``).
        env: extra environment variables.
        base_env: the child's whole environment as given (the localhost-only settings are NOT applied, domain_id
            is ignored): a node started the way an integrator would start it.
    """

    def __init__(self, params_file: str | None = None, params: dict[str, Any] | None = None,
                 domain_id: int | None = None, node_name: str | None = None, env: dict[str, str] | None = None,
                 stop_timeout: float = 10.0, base_env: dict[str, str] | None = None,
                 module: str = "xmetro_ros.ros.node") -> None:
        self.params_file = params_file
        self.params = dict(params or {})
        self.domain_id = domain_id
        self.node_name = node_name
        self.extra_env = dict(env or {})
        self.stop_timeout = stop_timeout
        self.base_env = None if base_env is None else dict(base_env)
        self.module = module
        self.lines: list[str] = []
        self.proc: Any = None
        self._ready = threading.Event()
        self._reader: threading.Thread | None = None

    def command(self) -> list[str]:
        import sys

        cmd = [sys.executable, "-m", self.module, "--ros-args"]
        if self.params_file:
            cmd += ["--params-file", str(self.params_file)]
        for k, v in self.params.items():
            val = str(v).lower() if isinstance(v, bool) else (f'"{v}"' if v == "" else str(v))
            cmd += ["-p", f"{k}:={val}"]
        if self.node_name:
            cmd += ["-r", f"__node:={self.node_name}"]
        return cmd

    def start(self, timeout: float = 60.0) -> NodeProcess:
        """Launch and wait for the ready line; raise RuntimeError (with the output) if it exits or times out."""
        import os
        import subprocess

        env = ros_env(self.domain_id) if self.base_env is None else dict(self.base_env)
        env.update(self.extra_env)
        env.setdefault("MALLOC_ARENA_MAX", "2")
        env.setdefault("OMP_NUM_THREADS", "2")
        env.setdefault("OPENBLAS_NUM_THREADS", "2")
        env["PYTHONUNBUFFERED"] = "1"
        self.proc = subprocess.Popen(self.command(), env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     text=True, bufsize=1, cwd=os.getcwd())

        def read() -> None:
            assert self.proc is not None and self.proc.stdout is not None
            for line in self.proc.stdout:
                self.lines.append(line.rstrip("\n"))
                if READY_MESSAGE in line:
                    self._ready.set()

        self._reader = threading.Thread(target=read, name="node-process-reader", daemon=True)
        self._reader.start()
        deadline = time.monotonic() + timeout
        while not self._ready.wait(0.1):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                out = "\n".join(self.lines[-40:])
                self.stop()
                raise RuntimeError(f"xmetro_node did not become ready (exit code {self.proc.returncode}):\n{out}")
        return self

    @property
    def pid(self) -> int:
        return int(self.proc.pid)

    def stop(self) -> int | None:
        """SIGINT, wait, SIGKILL if needed; return the exit code."""
        import signal
        import subprocess

        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(self.stop_timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5.0)
        if self._reader is not None:
            self._reader.join(timeout=5.0)
        return self.proc.returncode

    def __enter__(self) -> NodeProcess:
        return self.start() if self.proc is None else self

    def __exit__(self, *exc: object) -> None:
        self.stop()


class SequenceGaps:
    """Messages lost before a subscription's callback: gaps in each publisher's sequence numbers since its last
    received message (subscription history overflow, transport loss). A publisher's first received message sets its
    baseline (earlier ones may predate the subscription); at most ``keep`` publishers are remembered."""

    def __init__(self, keep: int = 256) -> None:
        self._last: OrderedDict[bytes, int] = OrderedDict()
        self._keep = keep

    def add(self, info: Any) -> int:
        """Take one message's info (rclpy's MessageInfo dict); return how many of its publisher's were lost."""
        try:
            seq = info.get("publication_sequence_number")
            gid = info.get("publisher_gid")
            key = bytes(gid["data"]) if gid else b""
        except (AttributeError, KeyError, TypeError):
            return 0
        if seq is None or not key:
            return 0
        last = self._last.get(key)
        lost = int(seq - last - 1) if last is not None and seq > last + 1 else 0
        if last is None or seq > last:
            self._last[key] = int(seq)
            self._last.move_to_end(key)
            while len(self._last) > self._keep:  # bounded: publishers come and go
                self._last.popitem(last=False)
        return lost

    def clear(self) -> None:
        """Forget every publisher (what was sent while not subscribed was not lost)."""
        self._last.clear()
