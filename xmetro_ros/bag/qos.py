"""``offered_qos_profiles`` as rosbag2 writes it (bag metadata version 9: Jazzy, Kilted).

rosbag2_storage (``qos.cpp``, ``yaml.hpp``) encodes a topic's offered profiles as a sequence with one mapping per
publisher: ``history``, ``depth``, ``reliability``, ``durability``, ``deadline``, ``lifespan``, ``liveliness``,
``liveliness_lease_duration``, ``avoid_ros_namespace_conventions``; policies as rmw's lowercase names
(``keep_last``, ``reliable``, ``transient_local``, ``automatic``, ``unknown``...), durations as ``{sec, nsec}``
(infinite = 9223372036 s 854775807 ns). Where it goes:

- ``metadata.yaml`` (version 9): the sequence itself (version ≤ 8 wrote a YAML *string* with integer enums; a v9
  reader — rosbag2's ``decode_for_version`` — rejects a string there);
- MCAP channel metadata ``offered_qos_profiles``: that sequence dumped to a YAML string (MCAP metadata is string →
  string); ``[]`` when there is none (yaml-cpp's dump of an empty sequence).

Older forms (integer enums, Foxy's "infinite" durations) are read and normalised to v9 as rosbag2 does.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import yaml

from .qos_profiles import INFINITE_NS

__all__ = ["INFINITE_NS", "normalize_qos", "offered_qos_list", "offered_qos_yaml", "parse_offered_qos",
           "qos_to_dict"]

_KEYS = ("history", "depth", "reliability", "durability", "deadline", "lifespan", "liveliness",
         "liveliness_lease_duration", "avoid_ros_namespace_conventions")
# rmw enum values (metadata version <= 8 stored these integers) → rmw_qos_*_policy_to_str names (version 9)
_ENUMS = {
    "history": ("system_default", "keep_last", "keep_all", "unknown"),
    "reliability": ("system_default", "reliable", "best_effort", "unknown", "best_available"),
    "durability": ("system_default", "transient_local", "volatile", "unknown", "best_available"),
    "liveliness": ("system_default", "automatic", "unknown", "manual_by_topic", "unknown", "best_available"),
}
# "Infinite" as Foxy-era RMWs reported it; rosbag2 reads them as RMW_DURATION_INFINITE (qos.cpp).
_FOXY_INFINITE = {(0x7FFFFFFF, 0xFFFFFFFF), (0x7FFFFFFF, 0x7FFFFFFF)}


def _duration_ns(ns: int) -> dict[str, int]:
    # rmw's "default" (0) means unset, which the ROS graph reports as infinite: record it so.
    ns = INFINITE_NS if ns <= 0 or ns >= INFINITE_NS else int(ns)
    sec, nsec = divmod(ns, 1_000_000_000)
    return {"sec": int(sec), "nsec": int(nsec)}


def _policy(value: Any) -> str:
    name = getattr(value, "name", value)
    return str(name).lower()


def normalize_qos(item: Mapping[str, Any]) -> dict[str, Any]:
    """One mapping in any rosbag2 form (v4–v9) → the v9 form, keys in rosbag2's order.

    Raises ValueError when a key is missing or a policy is not a known integer/name.
    """
    missing = [k for k in _KEYS if k not in item]
    if missing:
        raise ValueError(f"QoS mapping lacks {missing}")
    out: dict[str, Any] = {}
    for k in _KEYS:
        v = item[k]
        if k in _ENUMS:
            if isinstance(v, bool) or not isinstance(v, (int, str)):
                raise ValueError(f"QoS {k} {v!r} is neither an rmw enum value nor a name")
            if isinstance(v, int):
                if not 0 <= v < len(_ENUMS[k]):
                    raise ValueError(f"QoS {k} {v} is not an rmw enum value")
                v = _ENUMS[k][v]
            v = str(v).lower()
        elif k in ("deadline", "lifespan", "liveliness_lease_duration"):
            sec, nsec = int(v["sec"]), int(v["nsec"])
            if (sec, nsec) in _FOXY_INFINITE:
                sec, nsec = divmod(INFINITE_NS, 1_000_000_000)
            v = {"sec": sec, "nsec": nsec}
        elif k == "depth":
            v = int(v)
        else:
            v = bool(v)
        out[k] = v
    return out


def qos_to_dict(profile: Any) -> dict[str, Any]:
    """An rclpy ``QoSProfile`` (e.g. from ``get_publishers_info_by_topic``) or a mapping → rosbag2's v9 dict."""
    if isinstance(profile, Mapping):
        return normalize_qos(profile)
    return {
        "history": _policy(profile.history),
        "depth": int(profile.depth),
        "reliability": _policy(profile.reliability),
        "durability": _policy(profile.durability),
        "deadline": _duration_ns(profile.deadline.nanoseconds),
        "lifespan": _duration_ns(profile.lifespan.nanoseconds),
        "liveliness": _policy(profile.liveliness),
        "liveliness_lease_duration": _duration_ns(profile.liveliness_lease_duration.nanoseconds),
        "avoid_ros_namespace_conventions": bool(profile.avoid_ros_namespace_conventions),
    }


def offered_qos_list(profiles: Iterable[Any] | str | None) -> list[dict[str, Any]]:
    """Profiles (rclpy QoSProfiles, mappings, or an ``offered_qos_profiles`` string of any version) → v9 list."""
    if profiles is None:
        return []
    if isinstance(profiles, str):
        return [normalize_qos(p) for p in parse_offered_qos(profiles)]
    return [qos_to_dict(p) for p in profiles]


def offered_qos_yaml(profiles: Iterable[Any] | str | None) -> str:
    """The channel metadata string: the v9 list as block YAML (``[]`` when empty, as yaml-cpp dumps it)."""
    items = offered_qos_list(profiles)
    if not items:
        return "[]"
    return yaml.safe_dump(items, sort_keys=False, default_flow_style=False).strip()


def parse_offered_qos(text: str) -> list[dict[str, Any]]:
    """Parse an ``offered_qos_profiles`` string as stored (either rosbag2 form: integers before v9, names since)."""
    if not text or not text.strip():
        return []
    data = yaml.safe_load(text)
    if data is None:
        return []
    if not isinstance(data, list):
        raise ValueError(f"offered_qos_profiles is not a YAML list: {text[:80]!r}")
    return data
