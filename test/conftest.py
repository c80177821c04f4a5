"""Test session set-up: private network namespace (when root) and localhost-only ROS 2 settings.

When pytest is started directly as root outside a private network namespace, it re-executes itself through
tools/netns_run, so no DDS packet of the tests can reach another interface. Every test process (and every child it
starts) gets ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, our Fast DDS profile and a ROS_DOMAIN_ID fresh for this run.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"

from xmetro_ros.ros.dds_env import apply_ros_env  # noqa: E402


def pytest_configure(config) -> None:
    if "XMETRO_IN_NETNS" not in os.environ and os.geteuid() == 0:
        # Give the terminal back (pytest captures fds while loading conftests), then re-execute in a private netns.
        capman = config.pluginmanager.getplugin("capturemanager")
        if capman is not None:
            capman.suspend_global_capture(in_=True)
        sys.stdout.flush()
        sys.stderr.flush()
        runner = str(ROOT / "tools" / "netns_run")
        os.execv(runner, [runner, sys.executable, "-m", "pytest", *config.invocation_params.args])
    apply_ros_env()


def shared_data() -> Path:
    """../shared/data next to the repository (read-only real data)."""
    return SHARED / "data"
