"""Helpers for ROS 2 tests: nodes in this process, peers in separate processes, waiting for DDS matching.

- :func:`spin_node`: a plain rclpy node spinning in a background thread on its own context (ros.rclpy_util.NodeSpinner).
- :class:`PeerProcess`: a helper script started as a separate process with ``ros_env.ros_env()``; waits for the
  line ``READY`` on its stdout; closing its stdin asks it to exit (it also exits on its own after a lifetime).
- :func:`wait_subscribers` / :func:`wait_publishers`: block until DDS has matched the other side (discovery is
  asynchronous; publishing before the match loses volatile messages).
- :class:`Inbox`: a subscription that keeps what it receives; :meth:`Inbox.wait` for a message matching a predicate.
- :func:`publish_until`: publish until a matching reply arrives (robust to a reply writer matched late).

Every wait has a generous timeout (30 s by default) and raises ``TimeoutError`` with what was (not) seen; nothing
asserts on timing.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from xmetro_ros.ros.dds_env import ros_env
from xmetro_ros.ros.rclpy_util import NodeSpinner, wait_for

ROOT = Path(__file__).resolve().parents[1]
TIMEOUT = 30.0


def qos(depth: int = 5, latched: bool = False) -> QoSProfile:
    """Reliable QoS; ``latched`` = transient local (late joiners get the last ``depth`` messages)."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


def spin_node(name: str, **node_kwargs: Any) -> NodeSpinner:
    """A plain node ``name`` spinning in a daemon thread; close it (or use ``with``) when done."""
    return NodeSpinner(lambda ctx: Node(name, context=ctx, **node_kwargs))


def wait_subscribers(pub: Any, n: int = 1, timeout: float = TIMEOUT) -> None:
    """Wait until publisher ``pub`` is matched with at least ``n`` subscriptions."""
    if not wait_for(lambda: pub.get_subscription_count() >= n, timeout):
        raise TimeoutError(f"{pub.topic_name}: {pub.get_subscription_count()} subscriptions matched after "
                           f"{timeout:g} s, expected {n}")


def wait_publishers(sub: Any, n: int = 1, timeout: float = TIMEOUT) -> None:
    """Wait until subscription ``sub`` is matched with at least ``n`` publishers."""
    if not wait_for(lambda: sub.get_publisher_count() >= n, timeout):
        raise TimeoutError(f"{sub.topic_name}: {sub.get_publisher_count()} publishers matched after {timeout:g} s, "
                           f"expected {n}")


class Inbox:
    """Subscription on ``node`` that stores every message received on ``topic``."""

    def __init__(self, node: Node, msg_type: type, topic: str, qos_profile: QoSProfile | None = None) -> None:
        self.messages: list[Any] = []
        self._cond = threading.Condition()
        self.sub = node.create_subscription(msg_type, topic, self._on_msg, qos_profile or qos())

    def _on_msg(self, msg: Any) -> None:
        with self._cond:
            self.messages.append(msg)
            self._cond.notify_all()

    def wait(self, pred: Callable[[Any], bool] = lambda _m: True, timeout: float = TIMEOUT) -> Any:
        """First received message with ``pred(msg)`` true (waiting up to ``timeout`` s for it)."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                for m in self.messages:
                    if pred(m):
                        return m
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError(f"{self.sub.topic_name}: no matching message in {timeout:g} s "
                                       f"({len(self.messages)} received)")
                self._cond.wait(min(remaining, 0.5))


def publish_until(pub: Any, msg: Any, inbox: Inbox, pred: Callable[[Any], bool] = lambda _m: True,
                  timeout: float = TIMEOUT, period: float = 3.0) -> Any:
    """Publish ``msg`` (after the publisher is matched), re-publishing every ``period`` s until ``inbox`` holds a
    message with ``pred`` true; return it."""
    deadline = time.monotonic() + timeout
    wait_subscribers(pub, timeout=timeout)
    while True:
        pub.publish(msg)
        try:
            return inbox.wait(pred, timeout=min(period, max(0.1, deadline - time.monotonic())))
        except TimeoutError:
            if time.monotonic() >= deadline:
                raise


class PeerProcess:
    """``python <script> <args>`` in a separate process with the localhost-only ROS environment.

    The script prints ``READY`` when its entities exist and exits when its stdin is closed. Use as a context
    manager or call :meth:`close`; :attr:`output` has its stdout/stderr lines (for failure messages).
    """

    def __init__(self, script: str | Path, *args: str, timeout: float = 60.0, env: dict[str, str] | None = None):
        self.output: list[str] = []
        self.ready = False
        self._ready = threading.Event()
        self.proc = subprocess.Popen(
            [sys.executable, str(script), *args],
            env=env if env is not None else ros_env(),
            cwd=str(ROOT),
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        self._ready.wait(timeout)
        if not self.ready:
            out = self.text()
            self.close()
            raise TimeoutError(f"peer {script} not ready within {timeout:g} s; output:\n{out}")

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.output.append(line.rstrip("\n"))
            if line.strip() == "READY":
                self.ready = True
                self._ready.set()
        self._ready.set()  # EOF: unblock the waiter (the constructor checks poll())

    def text(self) -> str:
        return "\n".join(self.output[-50:])

    def close(self, timeout: float = 15.0) -> int | None:
        """Ask the peer to exit (stdin EOF), then terminate / kill it by pid if it lingers; return its exit code."""
        if self.proc.poll() is None:
            try:
                assert self.proc.stdin is not None
                self.proc.stdin.close()
            except OSError:
                pass
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.terminate()
                try:
                    self.proc.wait(5)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait(5)
        self._reader.join(5)
        return self.proc.returncode

    def __enter__(self) -> PeerProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def peer_stop_event(lifetime_s: float, grace_s: float = 10.0) -> threading.Event:
    """In a peer script: an event set when stdin closes (the test is done) or after ``lifetime_s``.

    The peer should then shut down cleanly; if it is still alive ``grace_s`` later (stuck in DDS shutdown), the
    process hard-exits, so that a peer can never outlive the test that started it.
    """
    stop = threading.Event()

    def read_stdin() -> None:
        try:
            sys.stdin.read()
        finally:
            stop.set()

    def watchdog() -> None:
        stop.wait(lifetime_s)
        stop.set()
        time.sleep(grace_s)
        sys.stdout.flush()
        os._exit(3)

    threading.Thread(target=read_stdin, daemon=True).start()
    threading.Thread(target=watchdog, daemon=True).start()
    return stop
