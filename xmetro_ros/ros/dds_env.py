"""Localhost-only DDS environment: an explicit opt-in for our tests, demo and benchmarks — never for the product.

The product (``xmetro_node``, ``xmetro_lifecycle_node``, ``xmetro record``, ``xmetro replay``) honours the
environment it is started in: ``ROS_DOMAIN_ID``, ``ROS_AUTOMATIC_DISCOVERY_RANGE``, ``ROS_STATIC_PEERS``,
``RMW_IMPLEMENTATION``, ``FASTDDS_DEFAULT_PROFILES_FILE`` are left as they are. Only when
``XMETRO_LOCALHOST_ONLY=1`` is set (``make test``/``demo``/``bench`` and tools/netns_run set it; the test harness,
``xmetro demo`` and the bench scripts apply it themselves), or ``--localhost-only`` is given, is this applied:

- ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``: discovery only on this host.
- a private ``ROS_DOMAIN_ID`` (fresh per test run / demo unless the caller set one).
- ``FASTDDS_DEFAULT_PROFILES_FILE``: config/fastdds_localhost.xml (shared memory + UDP on 127.0.0.1 only). The
  wheels carry Fast DDS 3, which reads only this name (the old FASTRTPS_ name is removed, so it cannot override).
- ``RMW_IMPLEMENTATION=rmw_fastrtps_cpp`` (the only RMW available from the wheels).
Tests and the demo additionally run inside a private network namespace when root (tools/netns_run).
:func:`apply_ros_env` and :func:`ros_env` also set ``XMETRO_LOCALHOST_ONLY=1``, so every child process inherits the
opt-in.
"""

from __future__ import annotations

import os
from collections.abc import Mapping

from ..scan.resources import config_path

__all__ = [
    "DDS_ENV_KEYS",
    "DDS_PROFILE_NAME",
    "LOCALHOST_FLAG",
    "LOCALHOST_ONLY_ENV",
    "apply_requested_ros_env",
    "apply_ros_env",
    "dds_env_summary",
    "fresh_domain_id",
    "localhost_only_requested",
    "pop_localhost_flag",
    "ros_env",
]

DDS_PROFILE_NAME = "fastdds_localhost.xml"
#: The opt-in variable: "1" (or true/yes/on) makes our programs apply the localhost-only environment.
LOCALHOST_ONLY_ENV = "XMETRO_LOCALHOST_ONLY"
#: The command-line form of the opt-in (``xmetro_node --localhost-only --ros-args ...``, ``xmetro record``).
LOCALHOST_FLAG = "--localhost-only"
#: The variables that decide which DDS peers a participant can reach.
DDS_ENV_KEYS = ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_STATIC_PEERS", "RMW_IMPLEMENTATION",
                "FASTDDS_DEFAULT_PROFILES_FILE", "ROS_LOCALHOST_ONLY")


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
    env[LOCALHOST_ONLY_ENV] = "1"  # children started with this environment keep the opt-in
    return env


def apply_ros_env(domain_id: int | None = None) -> dict[str, str]:
    """Apply :func:`ros_env` to this process (before rclpy.init) and return the variables set."""
    env = ros_env(domain_id)
    keys = ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "FASTDDS_DEFAULT_PROFILES_FILE", "RMW_IMPLEMENTATION")
    os.environ.pop("ROS_STATIC_PEERS", None)
    os.environ.pop("FASTRTPS_DEFAULT_PROFILES_FILE", None)
    for k in keys:
        os.environ[k] = env[k]
    os.environ[LOCALHOST_ONLY_ENV] = "1"
    return {k: env[k] for k in keys}


def localhost_only_requested(env: Mapping[str, str] | None = None) -> bool:
    """True when ``XMETRO_LOCALHOST_ONLY`` in ``env`` (default os.environ) is 1/true/yes/on."""
    value = (os.environ if env is None else env).get(LOCALHOST_ONLY_ENV, "")
    return value.strip().lower() in ("1", "true", "yes", "on")


def apply_requested_ros_env(flag: bool = False) -> dict[str, str] | None:
    """Apply the localhost-only environment when opted in (``flag`` or ``XMETRO_LOCALHOST_ONLY``); else change
    nothing and return None."""
    if flag or localhost_only_requested():
        return apply_ros_env()
    return None


def pop_localhost_flag(argv: list[str]) -> tuple[list[str], bool]:
    """Remove ``--localhost-only`` from ``argv`` (only before ``--ros-args``); return (rest, found)."""
    end = argv.index("--ros-args") if "--ros-args" in argv else len(argv)
    found = LOCALHOST_FLAG in argv[:end]
    rest = [a for i, a in enumerate(argv) if not (i < end and a == LOCALHOST_FLAG)]
    return rest, found


def dds_env_summary(env: Mapping[str, str] | None = None) -> str:
    """One line naming the DDS-relevant variables as this process sees them (logged by the node at start)."""
    e = os.environ if env is None else env
    parts = [f"{k}={e[k]}" if k in e else f"{k} unset" for k in DDS_ENV_KEYS]
    return ", ".join(parts) + f"; localhost-only opt-in {'on' if localhost_only_requested(e) else 'off'}"
