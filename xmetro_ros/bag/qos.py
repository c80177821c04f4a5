"""``offered_qos_profiles`` channel metadata as rosbag2 writes it (bag metadata version 9, Jazzy and later).

A YAML list with one mapping per publisher: policies as lowercase names (``keep_last``, ``reliable``,
``transient_local``, ``automatic``), durations as ``{sec, nsec}`` (infinite = 9223372036 s 854775807 ns, i.e.
INT64_MAX ns), ``avoid_ros_namespace_conventions``. The C++ rosbag2 and ``rosbags`` read this form.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import yaml

__all__ = ["INFINITE_NS", "offered_qos_yaml", "parse_offered_qos", "qos_to_dict"]

INFINITE_NS = 2**63 - 1
_KEYS = ("history", "depth", "reliability", "durability", "deadline", "lifespan", "liveliness",
         "liveliness_lease_duration", "avoid_ros_namespace_conventions")


def _duration(ns: int) -> dict[str, int]:
    # 0 = "default" in rmw means unspecified/infinite for deadline, lifespan and lease duration.
    ns = INFINITE_NS if ns <= 0 or ns >= INFINITE_NS else int(ns)
    sec, nsec = divmod(ns, 1_000_000_000)
    return {"sec": int(sec), "nsec": int(nsec)}


def _policy(value: Any) -> str:
    name = getattr(value, "name", value)
    return str(name).lower()


def qos_to_dict(profile: Any) -> dict[str, Any]:
    """An rclpy ``QoSProfile`` (or a mapping already in rosbag2's form) → rosbag2's dict."""
    if isinstance(profile, Mapping):
        missing = [k for k in _KEYS if k not in profile]
        if missing:
            raise ValueError(f"QoS mapping lacks {missing}")
        return {k: profile[k] for k in _KEYS}
    return {
        "history": _policy(profile.history),
        "depth": int(profile.depth),
        "reliability": _policy(profile.reliability),
        "durability": _policy(profile.durability),
        "deadline": _duration(profile.deadline.nanoseconds),
        "lifespan": _duration(profile.lifespan.nanoseconds),
        "liveliness": _policy(profile.liveliness),
        "liveliness_lease_duration": _duration(profile.liveliness_lease_duration.nanoseconds),
        "avoid_ros_namespace_conventions": bool(profile.avoid_ros_namespace_conventions),
    }


def offered_qos_yaml(profiles: Iterable[Any] | str | None) -> str:
    """The ``offered_qos_profiles`` string: "" for none, a YAML string passed through, else YAML of the list."""
    if profiles is None:
        return ""
    if isinstance(profiles, str):
        return profiles
    items = [qos_to_dict(p) for p in profiles]
    if not items:
        return ""
    return yaml.safe_dump(items, sort_keys=False, default_flow_style=False).strip()


def parse_offered_qos(text: str) -> list[dict[str, Any]]:
    """Parse an ``offered_qos_profiles`` string (either rosbag2 form: integers before v9, names since)."""
    if not text:
        return []
    data = yaml.safe_load(text)
    if not isinstance(data, list):
        raise ValueError(f"offered_qos_profiles is not a YAML list: {text[:80]!r}")
    return data
