"""Record live ROS 2 topics into a bag: generic (raw CDR) subscriptions by type name, like ``ros2 bag record``.

:class:`Recorder` owns an rclpy node. Every ``discovery_period`` seconds it lists the graph's topics and
subscribes to each new one that is requested (all topics when none were named) and whose type is installed here
(standard and our own types); others are skipped with a warning and listed in the summary. Subscriptions are
``raw=True`` (serialized bytes straight to the writer, no deserialization). The subscription QoS follows
rosbag2's adaptation: reliable only if every publisher offers reliable, transient-local only if every publisher
does; the publishers' offered profiles are stored as channel metadata. Log time = reception time (system clock).
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Iterable
from typing import Any

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from ..bag.codec import message_class
from ..bag.schema import UnknownTypeError
from ..bag.writer import BagWriter

__all__ = ["Recorder", "adapted_qos"]

log = logging.getLogger(__name__)


def adapted_qos(offered: list[QoSProfile], depth: int) -> QoSProfile:
    """The subscription QoS that matches every offered profile without dropping what they can deliver."""
    reliable = bool(offered) and all(p.reliability == ReliabilityPolicy.RELIABLE for p in offered)
    transient = bool(offered) and all(p.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in offered)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if transient else DurabilityPolicy.VOLATILE,
    )


class Recorder:
    """Subscribe to topics on ``node`` and write what arrives to ``writer``.

    Args:
        node: an rclpy node (the caller spins it).
        writer: the open bag writer (closed by the caller).
        topics: topic names to record; None or empty → every topic discovered.
        discovery_period: seconds between graph scans for new topics.
        qos_depth: subscription queue depth (size it for bursts of large clouds).
        exclude: topics never recorded.
    """

    def __init__(self, node: Node, writer: BagWriter, topics: Iterable[str] | None = None, *,
                 discovery_period: float = 1.0, qos_depth: int = 100, exclude: Iterable[str] = ()) -> None:
        self.node = node
        self.writer = writer
        self.wanted = {self._abs(t) for t in topics} if topics else None
        self.exclude = {self._abs(t) for t in exclude}
        self.qos_depth = int(qos_depth)
        self.subscriptions: dict[str, Any] = {}
        self.counts: Counter = Counter()
        self.unknown_types: dict[str, str] = {}  # topic → type name not installed here
        self.error: BaseException | None = None
        self.discover()
        self._timer = node.create_timer(discovery_period, self._discover_tick)

    def _discover_tick(self) -> None:
        self.discover()

    @staticmethod
    def _abs(topic: str) -> str:
        return topic if topic.startswith("/") else "/" + topic

    def discover(self) -> list[str]:
        """Subscribe to newly seen topics; return the ones added."""
        added = []
        for topic, types in self.node.get_topic_names_and_types():
            if topic in self.subscriptions or topic in self.unknown_types or topic in self.exclude:
                continue
            if self.wanted is not None and topic not in self.wanted:
                continue
            type_name = types[0]
            try:
                cls = message_class(type_name)
            except UnknownTypeError as e:
                self.unknown_types[topic] = type_name
                log.warning("not recording %s: %s", topic, e)
                continue
            infos = self.node.get_publishers_info_by_topic(topic)
            offered = [i.qos_profile for i in infos]
            if not offered:
                continue  # only subscribers so far: wait until a publisher tells us its QoS
            try:
                self.writer.add_topic(topic, type_name, offered)
            except UnknownTypeError as e:
                self.unknown_types[topic] = type_name
                log.warning("not recording %s: %s", topic, e)
                continue
            self.subscriptions[topic] = self.node.create_subscription(
                cls, topic, self._callback(topic), adapted_qos(offered, self.qos_depth), raw=True)
            added.append(topic)
            log.info("recording %s (%s)", topic, type_name)
        return added

    def _callback(self, topic: str) -> Any:
        def on_message(data: bytes, info: Any) -> None:
            if self.error is not None:
                return
            now = time.time_ns()
            try:
                pub = int(info.get("source_timestamp") or now) if isinstance(info, dict) else now
                self.writer.write(topic, data, now, pub)
                self.counts[topic] += 1
            except Exception as e:  # disk full etc.: stop recording, keep what was written
                self.error = e
                log.error("recording stopped: %s", e)

        return on_message

    def close(self) -> None:
        self.node.destroy_timer(self._timer)
        for sub in self.subscriptions.values():
            self.node.destroy_subscription(sub)
        self.subscriptions.clear()
