#!/usr/bin/env python3
"""How many DDS participants localhost discovery reaches on one host (docs/dds.md, "Participants per host").

Under ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` rmw_fastrtps announces a new participant to the first 32
participant ports of the domain on 127.0.0.1 (its UDP transport's ``maxInitialPeersRange``), not by multicast. This
script keeps K participants alive (one ROS context each, a node in it), starts a service in one more, and asks a
client in a separate process whether it sees the service within ``--timeout`` seconds, for each K given.

    tools/netns_run .venv/bin/python tools/discovery_limit.py [--k 0,31,32] [--timeout 10]

It applies the localhost-only settings (``xmetro_ros.ros.dds_env``: a fresh domain, our Fast DDS profile), as the
tests do; run it in a private network namespace (``tools/netns_run``) so nothing leaves the machine.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

SERVICE = "/xmetro_discovery_probe"


def client(timeout: float) -> int:
    """Child process: 0 when the probe service is found within ``timeout`` seconds, 1 otherwise."""
    import rclpy
    from std_srvs.srv import Trigger

    from xmetro_ros.ros.rclpy_util import new_context

    node = rclpy.create_node("discovery_probe_client", context=new_context())
    found = node.create_client(Trigger, SERVICE).wait_for_service(timeout_sec=timeout)
    return 0 if found else 1


def probe(k: int, timeout: float) -> tuple[bool, float]:
    """Keep ``k`` participants alive, serve the probe from one more; (found by a new process, seconds)."""
    from rclpy.node import Node
    from std_srvs.srv import Trigger

    from xmetro_ros.ros.rclpy_util import NodeSpinner

    def server(ctx) -> Node:
        node = Node("discovery_probe_server", context=ctx)
        node.create_service(Trigger, SERVICE, lambda _req, res: res)
        return node

    def filler(i: int) -> NodeSpinner:
        return NodeSpinner(lambda ctx: Node(f"discovery_filler_{i}", context=ctx))

    fillers = [filler(i) for i in range(k)]
    try:
        with NodeSpinner(server):
            t0 = time.monotonic()
            rc = subprocess.run([sys.executable, __file__, "--client", "--timeout", str(timeout)],
                                check=False).returncode
            return rc == 0, time.monotonic() - t0
    finally:
        for sp in fillers:
            sp.close()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--k", default="0,31,32", help="comma-separated numbers of participants kept alive")
    ap.add_argument("--timeout", type=float, default=10.0, help="seconds the client waits for the service")
    ap.add_argument("--client", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.client:
        return client(a.timeout)
    from xmetro_ros.ros.dds_env import apply_ros_env

    apply_ros_env()  # a fresh domain, LOCALHOST, our profile; inherited by the client process
    print(f"ROS_DOMAIN_ID={os.environ['ROS_DOMAIN_ID']} "
          f"ROS_AUTOMATIC_DISCOVERY_RANGE={os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE']}")
    for k in (int(v) for v in a.k.split(",")):
        found, seconds = probe(k, a.timeout)
        print(f"{k} participants alive, server is number {k + 1}: "
              f"{'found' if found else 'NOT found'} by a new process in {seconds:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
