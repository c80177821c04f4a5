"""Environment for every process that starts a DDS participant: traffic stays on this machine.

- ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``: discovery only on this host.
- a private ``ROS_DOMAIN_ID`` (fresh per test run / demo unless the caller set one).
- ``FASTDDS_DEFAULT_PROFILES_FILE``: config/fastdds_localhost.xml (shared memory + UDP on 127.0.0.1 only). The
  wheels carry Fast DDS 3, which reads only this name (the old FASTRTPS_ name is removed, so it cannot override).
- ``RMW_IMPLEMENTATION=rmw_fastrtps_cpp`` (the only RMW available from the wheels).
Tests and the demo additionally run inside a private network namespace when root (tools/netns_run).
"""

from __future__ import annotations

import os
from collections.abc import Mapping

from ..resources import config_path

__all__ = ["DDS_PROFILE_NAME", "apply_ros_env", "fresh_domain_id", "ros_env"]

DDS_PROFILE_NAME = "fastdds_localhost.xml"


def fresh_domain_id() -> int:
    """A domain id in 1..100 derived from the process id (0 is the default everybody else uses)."""
    return 1 + os.getpid() % 100


def ros_env(domain_id: int | None = None, base: Mapping[str, str] | None = None) -> dict[str, str]:
    """A copy of ``base`` (default: os.environ) with the localhost-only ROS settings applied.

    ``domain_id`` None keeps a ROS_DOMAIN_ID already set in ``base`` and otherwise picks a fresh one.
    """
    env = dict(os.environ if base is None else base)
    if domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(int(domain_id))
    elif "ROS_DOMAIN_ID" not in env:
        env["ROS_DOMAIN_ID"] = str(fresh_domain_id())
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.pop("ROS_STATIC_PEERS", None)
    profile = str(config_path(DDS_PROFILE_NAME))
    env.pop("FASTRTPS_DEFAULT_PROFILES_FILE", None)
    env["FASTDDS_DEFAULT_PROFILES_FILE"] = profile
    env["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
    return env


def apply_ros_env(domain_id: int | None = None) -> dict[str, str]:
    """Apply :func:`ros_env` to this process (before rclpy.init) and return the variables set."""
    env = ros_env(domain_id)
    keys = ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "FASTDDS_DEFAULT_PROFILES_FILE", "RMW_IMPLEMENTATION")
    os.environ.pop("ROS_STATIC_PEERS", None)
    os.environ.pop("FASTRTPS_DEFAULT_PROFILES_FILE", None)
    for k in keys:
        os.environ[k] = env[k]
    return {k: env[k] for k in keys}
