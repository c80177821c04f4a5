"""Our topics' QoS profiles (:mod:`xmetro_ros.bag.qos_profiles`, plain dicts in rosbag2's form) as rclpy
``QoSProfile`` objects."""

from __future__ import annotations

from typing import Any

from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile, ReliabilityPolicy

from ..bag.qos_profiles import INFINITE_NS

__all__ = ["as_rclpy"]


def as_rclpy(d: dict[str, Any]) -> Any:
    """The ``rclpy.qos.QoSProfile`` for a mapping of this module (durations: infinite → rmw's default)."""
    def dur(v: dict[str, int]) -> Duration:
        ns = int(v["sec"]) * 1_000_000_000 + int(v["nsec"])
        return Duration(nanoseconds=0 if ns >= INFINITE_NS else ns)

    return QoSProfile(
        history=HistoryPolicy[d["history"].upper()],
        depth=int(d["depth"]),
        reliability=ReliabilityPolicy[d["reliability"].upper()],
        durability=DurabilityPolicy[d["durability"].upper()],
        deadline=dur(d["deadline"]),
        lifespan=dur(d["lifespan"]),
        liveliness=LivelinessPolicy[d["liveliness"].upper()],
        liveliness_lease_duration=dur(d["liveliness_lease_duration"]),
        avoid_ros_namespace_conventions=bool(d["avoid_ros_namespace_conventions"]),
    )
