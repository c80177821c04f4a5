"""`xmetro bag recover`: a SIGKILLed recording (real recorder process) becomes a complete bag that rosbags and the
mcap library's indexed reader open, with every message our damage-tolerant reader gets from the killed file."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from std_msgs.msg import String
from test_bag_recorder import _Proc, _publish_all

from xmetro_ros.bag import qos_profiles
from xmetro_ros.bag.qos import offered_qos_list
from xmetro_ros.bag.reader import BagReader
from xmetro_ros.bag.recover import chunk_compression, recover
from xmetro_ros.bag.writer import BagWriter
from xmetro_ros.ros.dds_env import ros_env


def _raw(path: Path) -> list[tuple[str, int, bytes]]:
    r = BagReader(path)
    return [(m.topic, m.log_time_ns, bytes(m.raw)) for m in r.messages(deserialize=False)]


def _rosbags_dir(path: Path) -> list[tuple[str, int, bytes]]:
    from rosbags.rosbag2 import Reader

    with Reader(path) as r:
        return [(c.topic, t, bytes(raw)) for c, t, raw in r.messages()]


def _mcap_indexed(path: Path) -> list[tuple[str, int, bytes]]:
    """The mcap library's reader on a seekable file: it goes through the summary and the chunk indexes."""
    with open(path, "rb") as f:
        r = make_reader(f)
        assert r.get_summary() is not None
        return [(ch.topic, m.log_time, bytes(m.data)) for _s, ch, m in r.iter_messages(log_time_order=False)]


def _rosbags_storage_fails(path: Path) -> bool:
    from rosbags.rosbag2.storage_mcap import McapReader

    st = McapReader(path)
    try:
        st.open()
    except Exception:
        return True
    st.close()
    return False


@pytest.mark.timeout(180)
def test_sigkilled_recording_recovers_every_completed_message(tmp_path: Path):
    """A recorder killed with 3 closed chunks + an open one: rosbags cannot open the file; after recover rosbags
    (directory, with metadata.yaml) and mcap's indexed reader read exactly what BagReader gets from the damaged
    file, with the recorded QoS of each topic."""
    out = tmp_path / "killed.mcap"
    proc = _Proc(["-o", str(out), "--chunk-size", "7000", "--discovery-period", "0.2", "--progress", "0.1",
                  "/k/chatter", "/k/other"])
    try:
        _publish_all({"/k/chatter": String, "/k/other": String}, proc, pad=2000)
        proc.p.send_signal(signal.SIGKILL)
        proc.finish()
    finally:
        proc.kill()
    assert proc.p.returncode == -signal.SIGKILL
    killed = BagReader(out)
    damaged = [(m.topic, m.log_time_ns, bytes(m.raw)) for m in killed.messages(deserialize=False)]
    assert killed.report.unfinished_files == [str(out)]
    assert len(damaged) >= 8  # the closed chunks
    assert _rosbags_storage_fails(out)  # "File end magic is invalid": the issue

    res = recover(out, tmp_path / "rec.mcap")
    assert res.messages == len(damaged)
    assert _mcap_indexed(tmp_path / "rec.mcap") == damaged
    assert not _rosbags_storage_fails(tmp_path / "rec.mcap")
    r = BagReader(tmp_path / "rec.mcap")
    assert _raw(tmp_path / "rec.mcap") == damaged and r.report.ok

    res = recover(out, tmp_path / "recdir")
    assert res.metadata_yaml == tmp_path / "recdir" / "metadata.yaml"
    assert _rosbags_dir(tmp_path / "recdir") == damaged
    # the QoS the recorder stored (the test publisher's, from the graph) survives, in v9 form
    q = offered_qos_list(BagReader(tmp_path / "recdir").offered_qos("/k/chatter"))
    assert q and q[0]["reliability"] == "reliable" and q[0]["durability"] == "volatile"


@pytest.mark.timeout(180)
def test_sigkilled_split_directory_recovers_with_metadata_yaml(tmp_path: Path):
    """A killed rosbag2-directory recording (split files, no metadata.yaml yet) → a directory rosbags opens."""
    out = tmp_path / "split"
    proc = _Proc(["-o", str(out), "--chunk-size", "3000", "--split-size", "0.012", "--discovery-period", "0.2",
                  "--progress", "0.1", "/d/chatter"])
    try:
        _publish_all({"/d/chatter": String}, proc, pad=2000)
        proc.p.send_signal(signal.SIGKILL)
        proc.finish()
    finally:
        proc.kill()
    assert not (out / "metadata.yaml").exists() and len(list(out.glob("*.mcap"))) >= 2
    damaged = _raw(out)
    assert len(damaged) >= 8
    res = recover(out, tmp_path / "fixed")
    assert sorted(p.name for p in (tmp_path / "fixed").glob("*.mcap")) == sorted(p.name for p in out.glob("*.mcap"))
    assert _rosbags_dir(tmp_path / "fixed") == damaged == _raw(tmp_path / "fixed")
    assert res.messages == len(damaged)


@pytest.mark.parametrize("compression", [None, "zstd"])
def test_cut_inside_a_chunk(tmp_path: Path, compression: str | None):
    """A file cut in the middle of a chunk: the messages of the complete chunks (and, uncompressed, the complete
    messages at the start of the cut chunk) are recovered, in order, with the chunk compression kept."""
    p = tmp_path / "cut.mcap"
    with BagWriter(p, compression=compression, chunk_size=1000) as w:
        w.add_topic("/s", "std_msgs/msg/String", [qos_profiles.SETTINGS])
        for i in range(100):
            w.write("/s", String(data=f"{i:04d}" + "x" * 96), 1000 + i, 2000 + i)
    with open(p, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    mid = chunks[len(chunks) // 2]
    p.write_bytes(p.read_bytes()[: mid.chunk_start_offset + mid.chunk_length // 2])
    rep = BagReader(p)
    damaged = [(m.topic, m.log_time_ns, bytes(m.raw)) for m in rep.messages(deserialize=False)]
    if compression is None:
        assert rep.report.recovered_from_partial_chunk > 0
    res = recover(p, tmp_path / "out")
    assert _rosbags_dir(tmp_path / "out") == damaged
    assert [int(m[2][8:12]) for m in damaged] == list(range(len(damaged)))  # an in-order prefix
    assert chunk_compression(tmp_path / "out" / "cut.mcap") == (compression or "")
    assert res.files[0].report.lost  # the cut is reported
    with open(tmp_path / "out" / "cut.mcap", "rb") as f:
        pub = [m.publish_time - m.log_time for _s, _c, m in make_reader(f).iter_messages()]
    assert set(pub) == {1000}  # publish times kept


def test_recover_keeps_metadata_records_and_attachments(tmp_path: Path):
    """scan_io's bags carry a manifest record and per-scan attachments: a recovered copy reads back identically."""
    from xmetro_ros.ros.scan_io import read_manifest, read_scans, write_scans
    from xmetro_ros.scan.geometry import HeadPose
    from xmetro_ros.scan.scan import Scan
    from xmetro_ros.scan.scanner import ScanSettings

    head = HeadPose(np.array([0.0, 0.0, 90.0]), np.eye(3))
    pts = np.arange(30, dtype=np.float64).reshape(10, 3) + 100.0
    scans = [Scan(pts + i, ScanSettings(1000.0, 500.0, 2.0), head, "xm-ls90", {}, "artifact", 10**9 * (i + 1),
                  expected_error=np.full((10, 3), 0.001 * i)) for i in range(3)]
    write_scans(tmp_path / "a.mcap", scans, manifest={"campaign": "t"}, exact=True)
    recover(tmp_path / "a.mcap", tmp_path / "b.mcap")
    a, b = read_scans(tmp_path / "a.mcap"), read_scans(tmp_path / "b.mcap")
    assert len(a) == len(b) == 3
    for x, y in zip(a, b, strict=True):
        assert np.array_equal(x.points, y.points) and np.array_equal(x.expected_error, y.expected_error)
        assert x.settings == y.settings and x.stamp_ns == y.stamp_ns
    assert read_manifest(tmp_path / "b.mcap") == {"campaign": "t"}


def test_cli_recover(tmp_path: Path):
    p = tmp_path / "k.mcap"
    with BagWriter(p, chunk_size=500) as w:
        w.add_topic("/s", "std_msgs/msg/String")
        for i in range(30):
            w.write("/s", String(data="y" * 100), i)
    with open(p, "rb") as f:
        last = make_reader(f).get_summary().chunk_indexes[-1]
    p.write_bytes(p.read_bytes()[: last.chunk_start_offset + last.chunk_length])  # all after the last chunk gone
    cmd = [sys.executable, "-m", "xmetro_ros.apps.cli", "bag", "recover"]
    out = subprocess.run([*cmd, str(p), str(tmp_path / "r")], capture_output=True, text=True, env=ros_env(),
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert "30 messages recovered" in out.stdout and (tmp_path / "r" / "metadata.yaml").is_file()
    assert len(_rosbags_dir(tmp_path / "r")) == 30
    again = subprocess.run([*cmd, str(p), str(tmp_path / "r")], capture_output=True, text=True, env=ros_env(),
                           timeout=120)
    assert again.returncode == 2 and "already exists" in again.stderr
    (tmp_path / "junk.mcap").write_bytes(b"not a bag at all")
    bad = subprocess.run([*cmd, str(tmp_path / "junk.mcap"), str(tmp_path / "j.mcap")], capture_output=True,
                         text=True, env=ros_env(), timeout=120)
    assert bad.returncode == 1 and "not an MCAP file" in bad.stderr


@pytest.mark.parametrize("compression", [None, "zstd"])
def test_recover_at_every_cut_point(tmp_path: Path, compression: str | None):
    """A bag (two topics, several chunks, metadata record) cut at every 9th byte: recover never fails on a file
    BagReader accepts (and refuses what it refuses), and the indexed reader of the result gives exactly BagReader's
    messages of the cut file."""
    from xmetro_ros.bag.reader import BagFormatError

    src = tmp_path / "src.mcap"
    with BagWriter(src, compression=compression, chunk_size=400) as w:
        w.add_topic("/a", "std_msgs/msg/String", [qos_profiles.SETTINGS])
        w.add_topic("/b", "std_msgs/msg/String", [qos_profiles.CLOUD])
        for i in range(24):
            w.write("/a" if i % 3 else "/b", String(data=f"{i:03d}" + "z" * (20 + 7 * i)), 100 + i)
    data = src.read_bytes()
    cut_file = tmp_path / "cut.mcap"
    checked = 0
    for cut in range(0, len(data), 9):
        cut_file.write_bytes(data[:cut])
        out = tmp_path / f"out_{cut}.mcap"
        try:
            expected = _raw(cut_file)
        except BagFormatError:
            with pytest.raises(BagFormatError):
                recover(cut_file, out)
            continue
        recover(cut_file, out)
        assert _mcap_indexed(out) == expected, cut
        out.unlink()
        checked += 1
    assert checked > len(data) // 9 - 3
    assert len(_raw(src)) == 24
