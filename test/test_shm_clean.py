"""A killed node's shared-memory segment and Fast DDS's cleaner (docs/dds.md, "Shared memory left by killed
processes").

Our Fast DDS profile gives every participant a 64 MB shared-memory segment in /dev/shm. A process killed with
SIGKILL (or crashing) cannot remove it, and Fast DDS never does it for it: the segment holds its memory until the
host reboots. ``fastdds shm clean``, the tool the Fast DDS wheel installs, removes the segments whose owner is gone
and none in use; it needs ``psutil`` (a dependency of ours for this) and the environment's ``python3``.
"""

from __future__ import annotations

import os
import signal
from pathlib import Path

from conftest import _port_segments, fastdds_shm_clean, remove_orphan_ports

from xmetro_ros.ros.rclpy_util import NodeProcess, NodeSpinner

SHM = Path("/dev/shm")
BIG = 32 << 20  # our profile's segments are 64 MB (+ allocator overhead); ports and default segments are < 1 MB


def big_segments() -> set[str]:
    return {p.name for p in SHM.glob("fastdds_*") if "port" not in p.name and not p.name.endswith(("_el", "_sl"))
            and p.stat().st_size > BIG}


def test_a_killed_nodes_segment_stays_until_fastdds_shm_clean() -> None:
    from rclpy.node import Node

    before = big_segments()
    with NodeSpinner(lambda ctx: Node("xmetro_shm_live", context=ctx)):
        live = big_segments() - before
        assert len(live) == 1, live  # this process's live participant's segment
        proc = NodeProcess().start()
        killed = big_segments() - before - live
        assert len(killed) == 1, (live, killed)  # the node process's own segment
        os.kill(proc.pid, signal.SIGKILL)
        proc.proc.wait(10.0)
        assert killed <= big_segments(), "Fast DDS removed a killed process's segment by itself"
        report = fastdds_shm_clean(check=True)
        left = big_segments()
        assert not killed & left, report
        assert live <= left, f"the cleaner removed a live participant's segment: {report}"


def test_orphan_port_segments_of_the_session_are_removed(tmp_path: Path) -> None:
    """A port segment the session created with no listener's lock file goes, with its mutex; one that was there
    before, or that a live listener holds (its ``_el`` lock file), stays."""
    for name in ("fastdds_port1", "fastdds_port2", "sem.fastdds_port2_mutex", "fastdds_port3", "fastdds_port3_el",
                 "fastdds_port3_sl"):
        (tmp_path / name).write_bytes(b"")
    before = {"fastdds_port1"}
    assert _port_segments(tmp_path) == {"fastdds_port1", "fastdds_port2", "fastdds_port3"}
    assert remove_orphan_ports(before, tmp_path) == ["fastdds_port2"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fastdds_port1", "fastdds_port3", "fastdds_port3_el",
                                                          "fastdds_port3_sl"]
