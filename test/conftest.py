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
    fastdds_shm_clean()
    global _PORTS_BEFORE
    _PORTS_BEFORE = _port_segments()
    _warm_kernels()


def pytest_unconfigure(config) -> None:
    # The tests that SIGKILL a DDS process leave its 64 MB shared-memory segment behind (test_shm_clean.py); on a
    # machine that runs the suite again and again they would pile up in /dev/shm, holding its memory.
    fastdds_shm_clean()
    remove_orphan_ports(_PORTS_BEFORE)


_SHM = Path("/dev/shm")
_PORTS_BEFORE: set[str] = set()


def _port_segments(shm: Path = _SHM) -> set[str]:
    """Names of the Fast DDS port segments in ``shm`` (``fastdds_port<N>``, not their lock files)."""
    return {p.name for p in shm.glob("fastdds_port*") if p.name[len("fastdds_port"):].isdigit()}


def remove_orphan_ports(before: set[str], shm: Path = _SHM) -> list[str]:
    """Remove the port segments this session created that no process listens on: no ``_el`` / ``_sl`` lock file
    (a listening port always has one). ``fastdds shm clean`` finds ports only through those lock files, so a
    segment re-created by a sender after its listener was SIGKILLed (test_bag_recorder.py) would stay for good.
    Returns the names removed."""
    removed = []
    for name in sorted(_port_segments(shm) - before):
        if (shm / f"{name}_el").exists() or (shm / f"{name}_sl").exists():
            continue
        for f in (shm / name, shm / f"sem.{name}_mutex"):
            f.unlink(missing_ok=True)
        removed.append(name)
    return removed


def fastdds_shm_clean(check: bool = False) -> str:
    """Run ``fastdds shm clean`` (the Fast DDS wheel's tool: removes the shared-memory segments and ports whose
    owner process is gone, none in use) with this environment's Python first on PATH, as the tool runs ``python3``
    and needs psutil. Returns its output; ``check`` raises on failure, else a failure only returns the message."""
    import subprocess

    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    try:
        out = subprocess.run(["fastdds", "shm", "clean"], env=env, capture_output=True, text=True, timeout=120)
    except (OSError, subprocess.TimeoutExpired) as e:
        if check:
            raise
        return f"fastdds shm clean failed: {e}"
    if check and out.returncode != 0:
        raise RuntimeError(f"fastdds shm clean exited with {out.returncode}: {out.stdout}{out.stderr}")
    return out.stdout + out.stderr


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


def at_one_and_two_numba_threads(fn):
    """(fn() at 1 numba thread, fn() at 2, or at the most numba has when fewer): for the tests that a compiled kernel
    gives the same bits at any thread count; numba's thread count is restored."""
    import numba

    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = fn()
        numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
        return one, fn()
    finally:
        numba.set_num_threads(before)
