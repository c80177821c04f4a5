"""Bags: rosbag2-format writing, reading others' bags, damage recovery, cross-check with rosbags."""

from __future__ import annotations

import dataclasses
import errno
import os
from pathlib import Path

import numpy as np
import pytest
import yaml
from builtin_interfaces.msg import Time
from conftest import need_shared
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header, String

from xmetro_ros.bag import schema
from xmetro_ros.bag.reader import BagFormatError, BagReader
from xmetro_ros.bag.writer import BagWriteError, BagWriter
from xmetro_ros.msg import ScannerSettings, ScanQuality
from xmetro_ros.ros.cloud import create_cloud_from_arrays

ROOT = Path(__file__).resolve().parents[1]
BAGS = ROOT.parent / "shared" / "data" / "bags"


# -- helpers ---------------------------------------------------------------------------------------------------
def _cloud(i: int, n: int = 50) -> PointCloud2:
    rng = np.random.default_rng(i)
    arrays = {k: rng.normal(size=n).astype(np.float32) for k in ("x", "y", "z", "intensity")}
    header = Header(stamp=Time(sec=i, nanosec=17), frame_id="artifact")
    return create_cloud_from_arrays(header, arrays, height=1, width=n)


def _settings(i: int) -> ScannerSettings:
    m = ScannerSettings(scanner_id="xm-ls90", lateral_density=1000.0 + i, direction_density=500.0,
                        exposure_time=0.002)
    m.header.frame_id = "artifact"
    m.header.stamp.sec = i
    m.head_pose.position.z = 0.09
    return m


def _quality(i: int) -> ScanQuality:
    q = ScanQuality(model_id="m", verdict=1, error_code=0, message=f"q{i}", points_received=10 + i,
                    flag_names=["OUTLIER", "GRAZING"], flag_counts=[i, 2 * i], usable_fraction=0.5)
    q.mean_abs_error = [1e-5, 2e-5, 3e-5 * i]
    q.settings = _settings(i)
    return q


def _messages(n: int = 6) -> list[tuple[str, str, object, int]]:
    out = []
    for i in range(n):
        t = 1_000_000_000 * (i + 1)
        out += [("/scan", "sensor_msgs/msg/PointCloud2", _cloud(i), t),
                ("/chatter", "std_msgs/msg/String", String(data=f"hello {i}"), t + 1),
                ("/scanner_settings", "xmetro_ros/msg/ScannerSettings", _settings(i), t + 2),
                ("/quality", "xmetro_ros/msg/ScanQuality", _quality(i), t + 3)]
    return out


def _write(path: Path, msgs, **kw) -> Path:
    qos = [QoSProfile(depth=7, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)]
    with BagWriter(path, **kw) as w:
        for topic, ty, _m, _t in msgs:
            w.add_topic(topic, ty, qos)
        for topic, _ty, m, t in msgs:
            w.write(topic, m, t)
    return path


def _as_plain(m) -> object:
    """rclpy or rosbags message → nested plain Python (dicts, lists, floats) for field-by-field comparison."""
    if hasattr(m, "get_fields_and_field_types"):
        return {k: _as_plain(getattr(m, k)) for k in m.get_fields_and_field_types()}
    if hasattr(m, "__msgtype__"):
        # rosbags keeps constants (upper case) and __msgtype__ as dataclass fields; rclpy does not
        return {f.name: _as_plain(getattr(m, f.name)) for f in dataclasses.fields(m)
                if not f.name.isupper() and not f.name.startswith("__")}
    if isinstance(m, (bytes, bytearray)):
        return list(m)
    if isinstance(m, np.ndarray) or hasattr(m, "tolist"):
        return [_as_plain(x) for x in np.asarray(m).tolist()] if np.ndim(m) else np.asarray(m).item()
    if isinstance(m, (list, tuple)) or type(m).__name__ == "array":
        return [_as_plain(x) for x in m]
    return m


# -- schema and metadata ---------------------------------------------------------------------------------------
def test_schema_text_equals_cpp_rosbag2_and_type_hash():
    need_shared(BAGS)
    with open(BAGS / "rosbag2_pointcloud2_truck" / "outlier.mcap_0.mcap", "rb") as f:
        sc = make_reader(f).get_summary().schemas[1]
    assert sc.name == "sensor_msgs/msg/PointCloud2" and sc.encoding == "ros2msg"
    assert schema.schema_text("sensor_msgs/msg/PointCloud2") == sc.data.decode()
    text = schema.schema_text("xmetro_ros/msg/ScanQuality")
    deps = [line[5:] for line in text.splitlines() if line.startswith("MSG: ")]
    assert deps == ["std_msgs/Header", "builtin_interfaces/Time", "xmetro_ros/ScannerSettings", "geometry_msgs/Pose",
                    "geometry_msgs/Point", "geometry_msgs/Quaternion"]
    assert schema.type_hash("sensor_msgs/msg/PointCloud2").startswith("RIHS01_")
    assert schema.type_hash("xmetro_ros/msg/ScannerSettings").startswith("RIHS01_")
    with pytest.raises(schema.UnknownTypeError):
        schema.schema_text("nope_msgs/msg/Nothing")


def test_written_file_has_rosbag2_layout(tmp_path):
    p = _write(tmp_path / "a.mcap", _messages(3), chunk_size=2000)
    with open(p, "rb") as f:
        r = make_reader(f)
        assert r.get_header().profile == "ros2"
        s = r.get_summary()
        md = {m.name: m.metadata for m in r.iter_metadata()}
    assert s.statistics.message_count == 12 and s.statistics.chunk_count > 1 and s.chunk_indexes
    assert {c.message_encoding for c in s.channels.values()} == {"cdr"}
    assert {sc.encoding for sc in s.schemas.values()} == {"ros2msg"}
    for ch in s.channels.values():
        assert ch.metadata["topic_type_hash"] == schema.type_hash(s.schemas[ch.schema_id].name)
        assert "reliability: reliable" in ch.metadata["offered_qos_profiles"]
    # As rosbag2_storage_mcap's update_metadata: the bare BagMetadata (version 9, ros_distro inside), no wrapper.
    meta = yaml.safe_load(md["rosbag2"]["serialized_metadata"])
    assert set(md["rosbag2"]) == {"serialized_metadata"}
    assert meta["version"] == 9 and meta["ros_distro"] == "kilted" and meta["message_count"] == 12
    assert isinstance(meta["topics_with_message_count"][0]["topic_metadata"]["offered_qos_profiles"], list)


def test_roundtrip_bare_and_split_directory(tmp_path):
    msgs = _messages(6)
    for path, kw in [(tmp_path / "bare.mcap", {}),
                     (tmp_path / "split", dict(compression="zstd", split_size=6000, chunk_size=1500))]:
        _write(path, msgs, **kw)
        r = BagReader(path)
        got = r.read_all()
        assert r.report.ok and r.report.messages == len(msgs)
        assert r.topics() == {t: ty for t, ty, _m, _t in msgs}
        assert [(m.topic, m.log_time_ns) for m in got] == [(t, ts) for t, _ty, _m, ts in msgs]
        for m, (_t, _ty, orig, _ts) in zip(got, msgs, strict=True):
            assert m.msg == orig
    assert len(BagReader(tmp_path / "split").files) > 1
    assert (tmp_path / "split" / "metadata.yaml").is_file()


def test_split_by_duration_and_bad_arguments(tmp_path):
    msgs = _messages(4)
    _write(tmp_path / "dur", msgs, split_duration=1.5)
    r = BagReader(tmp_path / "dur")
    assert len(r.files) == 2 and len(r.read_all()) == len(msgs)
    with pytest.raises(ValueError, match="directory"):
        BagWriter(tmp_path / "x.mcap", split_size=100)
    with pytest.raises(ValueError, match="compression"):
        BagWriter(tmp_path / "y.mcap", compression="lz5")
    with pytest.raises(FileExistsError):
        BagWriter(tmp_path / "dur")
    with BagWriter(tmp_path / "z.mcap") as w:
        with pytest.raises(KeyError, match="add_topic"):
            w.write("/nothing", String(), 0)
        with pytest.raises(schema.UnknownTypeError):
            w.add_topic("/t", "nope_msgs/msg/Nothing")


# -- bags written by others --------------------------------------------------------------------------------------
def test_reads_cpp_rosbag2_pointcloud_bag():
    need_shared(BAGS)
    r = BagReader(BAGS / "rosbag2_pointcloud2_truck")
    msgs = r.read_all()
    assert r.report.ok and len(msgs) == 3
    widths = {m.topic: m.msg.width for m in msgs}
    assert widths == {"cloud_1": 80256, "cloud_2": 35200, "cloud_3": 80256}
    for m in msgs:
        assert m.type_name == "sensor_msgs/msg/PointCloud2"
        assert m.msg.header.frame_id == "test" and m.msg.header.stamp.sec == 0 and m.msg.point_step == 12
    bare = BagReader(BAGS / "rosbag2_pointcloud2_truck" / "outlier.mcap_0.mcap")
    assert len(bare.read_all(deserialize=False)) == 3


def test_reads_rosbag2_talker_and_split_bags():
    need_shared(BAGS)
    r = BagReader(BAGS / "rosbag2_talker")
    msgs = r.read_all()
    assert r.report.ok and len(msgs) == 20
    assert next(m.msg.data for m in msgs if m.topic == "/topic") == "Hello, world! 0"
    split = BagReader(BAGS / "rosbag2_split_wbag")
    assert len(split.files) == 5
    n = sum(1 for _ in split.messages())
    assert n == 6074 and split.report.by_topic["AAA"] == 804 and split.report.ok


# -- independent reader/writer: rosbags ------------------------------------------------------------------------
def _rosbags_typestore():
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_KILTED)
    types = {}
    for name in ("ScannerSettings", "ScanQuality", "SettingsCandidate"):
        t = f"xmetro_ros/msg/{name}"
        types.update(get_types_from_msg(schema.msg_file(t).read_text(), t))
    store.register(types)
    return store


def test_rosbags_reads_our_bag_identically(tmp_path):
    from rosbags.highlevel import AnyReader

    msgs = _messages(4)
    _write(tmp_path / "ours", msgs, compression="zstd", chunk_size=3000)
    ours = BagReader(tmp_path / "ours").read_all()
    with AnyReader([tmp_path / "ours"], default_typestore=_rosbags_typestore()) as ar:
        theirs = [(c.topic, t, ar.deserialize(raw, c.msgtype)) for c, t, raw in ar.messages()]
        hashes = {c.topic: c.digest for c in ar.connections}
    assert len(theirs) == len(ours) == len(msgs)
    for o, (topic, t, m) in zip(ours, theirs, strict=True):
        assert (o.topic, o.log_time_ns) == (topic, t)
        assert _as_plain(o.msg) == _as_plain(m)
    assert hashes["/quality"] == schema.type_hash("xmetro_ros/msg/ScanQuality")


def test_our_reader_reads_rosbags_bag(tmp_path):
    from rclpy.serialization import serialize_message
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as RosbagsWriter

    store = _rosbags_typestore()
    msgs = _messages(3)
    with RosbagsWriter(tmp_path / "theirs", version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {}
        for topic, ty, _m, _t in msgs:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, ty, typestore=store)
        for topic, ty, m, t in msgs:
            # rosbags serializes its own objects: round-trip our message through it to make one.
            obj = store.deserialize_cdr(serialize_message(m), ty)
            w.write(conns[topic], t, store.serialize_cdr(obj, ty))
    r = BagReader(tmp_path / "theirs")
    got = r.read_all()
    assert r.report.ok and len(got) == len(msgs)
    for g, (_topic, _ty, m, t) in zip(got, msgs, strict=True):
        assert g.log_time_ns == t and g.msg == m


# -- bad input ----------------------------------------------------------------------------------------------------
def _string_bag(path: Path, n: int, compression: str | None, chunk_size: int = 1000) -> list[bytes]:
    payload = []
    with BagWriter(path, compression=compression, chunk_size=chunk_size) as w:
        w.add_topic("/s", "std_msgs/msg/String")
        for i in range(n):
            w.write("/s", String(data=f"{i:04d}" + "x" * 96), i)
    return payload


def _chunks(path: Path):
    with open(path, "rb") as f:
        return make_reader(f).get_summary().chunk_indexes


def test_truncated_bag_reads_every_complete_message(tmp_path):
    for compression in ("zstd", None):
        p = tmp_path / f"t_{compression}.mcap"
        _string_bag(p, 100, compression)
        chunks = _chunks(p)
        last = chunks[len(chunks) // 2]
        cut = last.chunk_start_offset + last.chunk_length // 2
        data = p.read_bytes()[:cut]
        p.write_bytes(data)
        r = BagReader(p)
        got = [int(m.msg.data[:4]) for m in r.messages()]
        complete = [c for c in chunks if c.chunk_start_offset + c.chunk_length <= cut]
        n_complete = max(c.message_end_time for c in complete) + 1
        assert got == list(range(len(got)))  # a prefix, in order
        if compression == "zstd":
            assert len(got) == n_complete and r.report.recovered_from_partial_chunk == 0
        else:
            # uncompressed chunk cut in the middle: its complete message records are recovered too
            records_start = last.chunk_start_offset + 9 + 40
            msg_record = 9 + 22 + len(r.read_all(deserialize=False)[0].raw)
            assert len(got) == n_complete + (cut - records_start) // msg_record
            assert r.report.recovered_from_partial_chunk == len(got) - n_complete > 0
        assert len(r.report.lost) == 1 and not r.report.ok
        lost = r.report.lost[0]
        assert lost.offset == last.chunk_start_offset and "truncated inside a chunk" in lost.reason
        assert (lost.start_ns, lost.end_ns) == (last.message_start_time, last.message_end_time)
        assert r.report.unfinished_files == [str(p)]
        assert "lost:" in r.report.describe()


def test_corrupted_chunk_is_skipped_and_counted(tmp_path):
    p = tmp_path / "c.mcap"
    _string_bag(p, 60, None)
    chunks = _chunks(p)
    bad = chunks[1]
    raw = bytearray(p.read_bytes())
    raw[bad.chunk_start_offset + bad.chunk_length - 30] ^= 0xFF  # inside the chunk's records
    p.write_bytes(bytes(raw))
    r = BagReader(p)
    got = [int(m.msg.data[:4]) for m in r.messages()]
    lost_ids = set(range(bad.message_start_time, bad.message_end_time + 1))
    assert got == [i for i in range(60) if i not in lost_ids]
    (lost,) = r.report.lost
    assert lost.messages == len(lost_ids) and "corrupted chunk" in lost.reason and "CRC" in lost.reason
    assert (lost.start_ns, lost.end_ns) == (bad.message_start_time, bad.message_end_time)


def test_empty_and_non_bags(tmp_path):
    (tmp_path / "zero.mcap").write_bytes(b"")
    with pytest.raises(BagFormatError, match="empty"):
        BagReader(tmp_path / "zero.mcap")
    (tmp_path / "text.mcap").write_text("hello, not a bag at all")
    with pytest.raises(BagFormatError, match="not an MCAP"):
        BagReader(tmp_path / "text.mcap")
    with pytest.raises(FileNotFoundError):
        BagReader(tmp_path / "missing.mcap")
    (tmp_path / "emptydir").mkdir()
    with pytest.raises(BagFormatError, match="neither"):
        BagReader(tmp_path / "emptydir")
    with BagWriter(tmp_path / "nomsg.mcap") as w:
        w.add_topic("/s", "std_msgs/msg/String")
    r = BagReader(tmp_path / "nomsg.mcap")
    assert r.topics() == {"/s": "std_msgs/msg/String"} and r.read_all() == [] and r.report.ok


def test_unknown_types_are_skipped_and_listed(tmp_path, caplog):
    from rclpy.serialization import serialize_message

    p = tmp_path / "u.mcap"
    with open(p, "wb") as f:
        w = Writer(f, compression=CompressionType.NONE)
        w.start(profile="ros2", library="test")
        s1 = w.register_schema("std_msgs/msg/String", "ros2msg", schema.schema_text("std_msgs/msg/String").encode())
        s2 = w.register_schema("acme_msgs/msg/Widget", "ros2msg", b"int32 a\n")
        c1 = w.register_channel("/s", "cdr", s1)
        c2 = w.register_channel("/w", "cdr", s2)
        for i in range(5):
            w.add_message(c1, i, serialize_message(String(data=str(i))), i)
            w.add_message(c2, i, b"\x00\x01\x00\x00\x07\x00\x00\x00", i)
        w.finish()
    r = BagReader(p)
    got = r.read_all()
    assert [m.msg.data for m in got] == ["0", "1", "2", "3", "4"]
    assert r.report.unknown_types == {"acme_msgs/msg/Widget": 5}
    assert "unknown type acme_msgs/msg/Widget" in r.report.describe()
    assert sum("acme_msgs/msg/Widget" in rec.getMessage() for rec in caplog.records) >= 1
    assert len(r.read_all(deserialize=False)) == 10  # raw reading keeps them


class _FillingDisk:
    """A file that accepts ``capacity`` bytes, then fails like a full disk (ENOSPC), keeping what fit."""

    def __init__(self, path: Path, capacity: int) -> None:
        self._f = open(path, "xb", buffering=0)
        self.capacity = capacity
        self.pos = 0
        self.closed = False

    def write(self, data) -> int:
        data = bytes(data)
        room = self.capacity - self.pos
        if len(data) > room:
            self._f.write(data[:room])
            self.pos += room
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self._f.write(data)
        self.pos += len(data)
        return len(data)

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:
        pass

    def close(self) -> None:
        self.closed = True
        self._f.close()


def test_disk_full_while_recording_keeps_what_was_written(tmp_path):
    p = tmp_path / "full.mcap"
    w = BagWriter(p, chunk_size=800, opener=lambda path: _FillingDisk(path, 5000))
    w.add_topic("/s", "std_msgs/msg/String")
    with pytest.raises(BagWriteError, match="No space left") as ei:
        for i in range(1000):
            w.write("/s", String(data=f"{i:04d}" + "x" * 96), i)
    assert ei.value.errno == errno.ENOSPC and "stay readable" in str(ei.value)
    with pytest.raises(BagWriteError, match="failed earlier"):
        w.write("/s", String(data="more"), 10_000)
    with pytest.raises(BagWriteError, match="after a write error"):
        w.close()
    assert p.stat().st_size == 5000
    r = BagReader(p)
    got = [int(m.msg.data[:4]) for m in r.messages()]
    assert len(got) > 20 and got == list(range(len(got)))
    assert r.report.unfinished_files == [str(p)] and r.report.lost
