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
    _warm_kernels()


def _warm_kernels() -> None:
    """Compile the judge's numba kernels into their on-disk cache once, before any test: the first compilation of
    the parallel kernels takes about a minute on a fresh clone (docs/performance.md), which would otherwise fall
    inside the first test that starts a node process and waits for it."""
    from xmetro_ros.judge import point_flags, scan_handler, set_kernels
    from xmetro_ros.ros import output_clouds

    scan_handler.warm_up()
    set_kernels.warm_up()
    point_flags.warm_up()
    output_clouds.warm_up()


#: Set by .ci/run: in CI a missing ../shared/data is a failure, never a silent skip.
REQUIRE_SHARED_ENV = "XMETRO_REQUIRE_SHARED_DATA"


def shared_data() -> Path:
    """../shared/data next to the repository (read-only real data)."""
    return SHARED / "data"


def need_shared(*paths: Path) -> Path:
    """Skip the calling test (or fixture) when real data it reads from ../shared/data is absent (a clone outside
    this environment), with the reason; under ``XMETRO_REQUIRE_SHARED_DATA=1`` (CI) fail instead. Returns the
    first path."""
    import pytest

    missing = [p for p in paths if not Path(p).exists()]
    if missing:
        why = (f"needs the real data {', '.join(map(str, missing))} (kept beside the repository in ../shared/data, "
               "see its README); absent here")
        if os.environ.get(REQUIRE_SHARED_ENV) == "1":
            pytest.fail(f"{why} and {REQUIRE_SHARED_ENV}=1: CI must never skip these tests", pytrace=False)
        pytest.skip(why)
    return Path(paths[0])
