"""pytest plugin: how many DDS participants of the test run's domain are alive around each test (docs/dds.md).

A participant listens on its metatraffic unicast UDP port, 7400 + 250 × domain + 10 + 2 × its participant id (RTPS
9.6.1.1), so the count is the number of such ports open in ``/proc/net/udp`` (this network namespace: the test
process and its children). Linux only. It prints the highest count and the test where it was seen at the end, and
writes one line per test set-up and teardown to ``XMETRO_PARTICIPANT_LOG`` when that is set.

    PYTHONPATH=tools .venv/bin/python -m pytest -p participant_count test/test_node_cell.py ...
"""

from __future__ import annotations

import os
from typing import Any

_MAX_IDS = 120
_peak: list[Any] = [0, ""]


def count_participants(domain: int | None = None) -> int:
    """The metatraffic unicast ports of ``domain`` (default ``ROS_DOMAIN_ID``) open in this network namespace."""
    d = int(os.environ.get("ROS_DOMAIN_ID", "0")) if domain is None else domain
    base = 7400 + 250 * d + 10
    ports = set()
    for path in ("/proc/net/udp", "/proc/net/udp6"):
        try:
            lines = open(path).read().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            port = int(line.split()[1].rsplit(":", 1)[1], 16)
            if base <= port < base + 2 * _MAX_IDS and (port - base) % 2 == 0:
                ports.add(port)
    return len(ports)


def _record(when: str, nodeid: str) -> None:
    n = count_participants()
    if n > _peak[0]:
        _peak[:] = [n, f"{when} {nodeid}"]
    log = os.environ.get("XMETRO_PARTICIPANT_LOG")
    if log:
        with open(log, "a") as f:
            f.write(f"{n:3d} {when} {nodeid}\n")


def pytest_runtest_setup(item: Any) -> None:
    _record("setup", item.nodeid)


def pytest_runtest_teardown(item: Any) -> None:
    _record("teardown", item.nodeid)


def pytest_terminal_summary(terminalreporter: Any) -> None:
    terminalreporter.write_line(f"participant_count: at most {_peak[0]} DDS participants alive ({_peak[1]})")
