"""`xmetro record` as a real process: discovery of all topics, SIGINT → complete bag, SIGKILL → chunks readable."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header, String

from xmetro_ros.bag.reader import BagReader
from xmetro_ros.msg import ScannerSettings
from xmetro_ros.ros.cloud import create_cloud_from_arrays
from xmetro_ros.ros.dds_env import ros_env
from xmetro_ros.ros.rclpy_util import NodeSpinner, wait_for

TIMEOUT = 30.0
N = 15


class _Proc:
    """The recorder process with its stdout collected line by line in a thread."""

    def __init__(self, args: list[str], wrap: list[str] | None = None, env: dict[str, str] | None = None) -> None:
        """``args`` of `xmetro record`; ``wrap``: a command the recorder's command line is appended to."""
        cmd = [*(wrap or []), sys.executable, "-m", "xmetro_ros.apps.record", "record", *args]
        self.p = subprocess.Popen(cmd, env={**ros_env(), **(env or {})}, stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT, text=True)
        self.lines: list[str] = []
        self._t = threading.Thread(target=self._read, daemon=True)
        self._t.start()

    def _read(self) -> None:
        for line in self.p.stdout:
            self.lines.append(line.rstrip("\n"))

    def saw(self, text: str) -> bool:
        return any(text in line for line in list(self.lines))

    def progress(self) -> dict[str, int]:
        last = [line for line in list(self.lines) if line.startswith("progress")]
        if not last:
            return {}
        return {k: int(v) for k, v in (kv.split("=") for kv in last[-1].split()[1:])}

    def finish(self, timeout: float = TIMEOUT) -> str:
        self.p.wait(timeout=timeout)
        self._t.join(timeout=5)
        return "\n".join(self.lines)

    def kill(self) -> None:
        if self.p.poll() is None:
            self.p.kill()
            self.p.wait(timeout=10)


def _publish_all(topics: dict[str, type], proc: _Proc, pad: int = 0) -> dict[str, list]:
    """Wait for the recorder to subscribe to every topic, publish N messages on each, wait until recorded.
    ``pad``: length the String messages are padded to."""
    sent: dict[str, list] = {t: [] for t in topics}
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    with NodeSpinner(lambda ctx: rclpy.create_node("bag_test_pub", context=ctx)) as sp:
        pubs = {t: sp.node.create_publisher(cls, t, qos) for t, cls in topics.items()}
        assert wait_for(lambda: all(proc.saw(f"subscribed {t} ") for t in topics), TIMEOUT), proc.lines
        assert wait_for(lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), TIMEOUT)
        for i in range(N):
            for t, cls in topics.items():
                if cls is String:
                    m = String(data=f"msg {i}".ljust(pad, "."))
                elif cls is ScannerSettings:
                    m = ScannerSettings(lateral_density=1000.0 + i, exposure_time=0.001)
                else:
                    xyz = {k: np.full(8, i, np.float32) for k in "xyz"}
                    m = create_cloud_from_arrays(Header(frame_id="artifact"), xyz, height=1, width=8)
                pubs[t].publish(m)
                sent[t].append(m)
        assert wait_for(lambda: all(proc.progress().get(t, 0) >= N for t in topics), TIMEOUT), proc.lines[-5:]
    return sent


@pytest.mark.timeout(120)
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_record_all_topics_stops_cleanly_on_signal(tmp_path: Path, sig: signal.Signals):
    out = tmp_path / "rec.mcap"
    proc = _Proc(["-o", str(out), "--discovery-period", "0.2", "--progress", "0.1"])
    try:
        topics = {"/rec/chatter": String, "/rec/settings": ScannerSettings, "/rec/cloud": PointCloud2}
        sent = _publish_all(topics, proc)
        proc.p.send_signal(sig)
        text = proc.finish()
    finally:
        proc.kill()
    assert proc.p.returncode == 0, text
    assert f"stopped ({sig.name})" in text
    r = BagReader(out)
    got = r.read_all()
    assert r.report.ok, r.report.describe()  # complete summary: footer written, nothing lost
    for t, msgs in sent.items():
        assert [m.msg for m in got if m.topic == t] == msgs
    assert r.topics()["/rec/cloud"] == "sensor_msgs/msg/PointCloud2"
    assert "reliability: reliable" in r.offered_qos("/rec/settings")
    assert r.topic_type_hash("/rec/settings").startswith("RIHS01_")


@pytest.mark.timeout(120)
@pytest.mark.parametrize("chunk,pad", [(1, 0), (7000, 2000)])
def test_sigkilled_recorder_keeps_every_closed_chunk(tmp_path: Path, chunk: int, pad: int):
    """After SIGKILL every closed chunk reads back, in order, and the reader says the file is unfinished.
    Chunk size 1 byte closes a chunk per message: everything recorded is on disk. 7,000-byte chunks of ~2 kB
    messages hold 4 messages each: 3 chunks of the 15 messages close, the 3 messages of the open chunk are lost."""
    out = tmp_path / "killed.mcap"
    proc = _Proc(["-o", str(out), "--chunk-size", str(chunk), "--discovery-period", "0.2", "--progress", "0.1",
                  "/k/chatter"])
    try:
        sent = _publish_all({"/k/chatter": String}, proc, pad=pad)["/k/chatter"]
        proc.p.send_signal(signal.SIGKILL)
        proc.finish()
    finally:
        proc.kill()
    assert proc.p.returncode == -signal.SIGKILL
    r = BagReader(out)
    got = [m.msg for m in r.messages()]
    assert got == sent[: len(got)]  # an in-order prefix: nothing garbled, nothing out of a closed chunk lost
    assert r.report.unfinished_files == [str(out)]
    if chunk == 1:
        assert len(got) == len(sent) and not r.report.lost
    else:
        assert 8 <= len(got) < len(sent)  # the closed chunks (>= 2 of 4 messages) are kept; the open one is lost


def _can_mount_tmpfs() -> bool:
    import os
    import shutil

    if os.geteuid() != 0 or not shutil.which("unshare"):
        return False
    return subprocess.run(["unshare", "-m", "sh", "-c", "mount -t tmpfs -o size=64k none /mnt"],
                          capture_output=True).returncode == 0


@pytest.mark.timeout(120)
@pytest.mark.skipif(not _can_mount_tmpfs(), reason="needs root to mount a small tmpfs in a private mount namespace")
def test_recorder_process_on_a_full_disk(tmp_path: Path):
    """The real `xmetro record` process writing to a real file system that fills up (a 96 KiB tmpfs in a private
    mount namespace; ~2 kB messages, 8 kB chunks): it stops with a clear 'No space left' error and exit code 1, and
    every message of the chunks written before is readable, in order."""
    outdir = tmp_path / "out"
    outdir.mkdir()
    disk = tmp_path / "disk"
    disk.mkdir()
    script = ('mount -t tmpfs -o size=96k none "$1" || exit 99; shift; '
              '"$@"; rc=$?; cp "$DISK/rec.mcap" "$OUTDIR/" 2>/dev/null; exit $rc')
    args = ["-o", str(disk / "rec.mcap"), "--chunk-size", "8000", "--discovery-period", "0.2", "--progress", "0.1",
            "/full/chatter"]
    proc = _Proc(args, wrap=["unshare", "-m", "sh", "-c", script, "sh", str(disk)],
                 env={"DISK": str(disk), "OUTDIR": str(outdir)})
    sent: list = []
    try:
        qos = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)
        with NodeSpinner(lambda ctx: rclpy.create_node("full_disk_pub", context=ctx)) as sp:
            pub = sp.node.create_publisher(String, "/full/chatter", qos)
            assert wait_for(lambda: proc.saw("subscribed /full/chatter "), TIMEOUT), proc.lines
            assert wait_for(lambda: pub.get_subscription_count() > 0, TIMEOUT)
            for i in range(100):  # ~200 kB: twice what the disk holds
                m = String(data=f"{i:04d}".ljust(2000, "x"))
                pub.publish(m)
                sent.append(m)
                if proc.p.poll() is not None:
                    break
                time.sleep(0.01)
            text = proc.finish()
    finally:
        proc.kill()
    assert proc.p.returncode == 1, text
    assert "No space left" in text, text
    r = BagReader(outdir / "rec.mcap")
    got = [m.msg for m in r.messages()]
    assert 8 <= len(got) < len(sent) and got == sent[: len(got)]
    assert r.report.unfinished_files
