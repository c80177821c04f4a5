"""The QoS our topics are offered with, as plain dicts in rosbag2's form (metadata version 9); no ROS import.

One place for these profiles so that the bag writers (scan_io, predict, replay, the recorder's fallbacks) record
the QoS a live publisher of that topic really offers, and so that ``ros2 bag play`` of our bags re-offers it
(rosbag2 plays a topic with its recorded profile, history reset to its default: ``adapt_offer_to_recorded_offers``):

- ``SETTINGS``: ``ScannerSettings`` — reliable + transient-local, so a node started after the settings were
  published still gets the latest ones (depth 10: one per frame/scanner for a few scanners).
- ``CLOUD``: an input ``PointCloud2`` scan — reliable + volatile. A reliable publisher matches reliable and
  best-effort subscriptions alike, so a replayed bag reaches any scan subscriber.
- ``cloud_output()`` / ``output()``: the node's outputs (``~/deviations``, ``~/corrected`` depth 2; ``~/quality``,
  ``/diagnostics`` depth 10) — reliable + volatile, as :func:`xmetro_ros.ros.node.output_qos` offers them.

Durations are ``{sec, nsec}``; "unset" (rmw's default 0) is written as infinite (9223372036 s 854775807 ns,
INT64_MAX ns) because that is what the ROS graph reports for a default profile and what rosbag2 records.
:func:`xmetro_ros.ros.qos.as_rclpy` turns a dict into an ``rclpy.qos.QoSProfile``.
"""

from __future__ import annotations

from typing import Any

__all__ = ["CLOUD", "INFINITE", "INFINITE_NS", "SETTINGS", "cloud_output", "output", "profile"]

INFINITE_NS = 2**63 - 1
INFINITE = {"sec": INFINITE_NS // 1_000_000_000, "nsec": INFINITE_NS % 1_000_000_000}


def profile(reliability: str = "reliable", durability: str = "volatile", depth: int = 10,
            history: str = "keep_last") -> dict[str, Any]:
    """A rosbag2 v9 QoS mapping (policy names as rmw's ``*_to_str``; deadline/lifespan/lease infinite)."""
    return {
        "history": history,
        "depth": int(depth),
        "reliability": reliability,
        "durability": durability,
        "deadline": dict(INFINITE),
        "lifespan": dict(INFINITE),
        "liveliness": "automatic",
        "liveliness_lease_duration": dict(INFINITE),
        "avoid_ros_namespace_conventions": False,
    }


SETTINGS: dict[str, Any] = profile("reliable", "transient_local", 10)
CLOUD: dict[str, Any] = profile("reliable", "volatile", 10)


def output(depth: int = 10) -> dict[str, Any]:
    """A node output (``~/quality``, ``/diagnostics``: depth 10)."""
    return profile("reliable", "volatile", depth)


def cloud_output() -> dict[str, Any]:
    """The node's cloud outputs ``~/deviations`` and ``~/corrected`` (depth 2: big messages)."""
    return output(2)
