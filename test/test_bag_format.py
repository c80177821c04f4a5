"""Our bags in exactly rosbag2's format (metadata version 9, as rosbag2 Jazzy/Kilted writes it), checked against
rosbag2's storage code (keys and order of ``convert<BagMetadata>::encode``, yaml.hpp; QoS encoding, qos.cpp; channel
metadata and ``rosbag2`` record, mcap_storage.cpp), against the bags rosbag2 itself wrote (../shared/data/bags) and
through an independent reader (rosbags); and every channel we write records the QoS its publisher really offers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rclpy
import yaml
from conftest import need_shared, shared_data
from mcap.reader import make_reader
from std_msgs.msg import String

from xmetro_ros.bag import qos_profiles
from xmetro_ros.bag.qos import offered_qos_list, offered_qos_yaml, parse_offered_qos, qos_to_dict
from xmetro_ros.bag.reader import BagReader
from xmetro_ros.bag.writer import BagWriter
from xmetro_ros.ros.qos import as_rclpy
from xmetro_ros.ros.rclpy_util import NodeSpinner, wait_for

# rosbag2_storage/include/rosbag2_storage/yaml.hpp (Jazzy = rolling 2024-10; bag_metadata.hpp: version = 9)
BAG_KEYS = ["version", "storage_identifier", "duration", "starting_time", "message_count",
            "topics_with_message_count", "compression_format", "compression_mode", "relative_file_paths", "files",
            "custom_data", "ros_distro"]
TOPIC_KEYS = ["name", "type", "serialization_format", "offered_qos_profiles", "type_description_hash"]
FILE_KEYS = ["path", "starting_time", "duration", "message_count"]
# rosbag2_storage/src/rosbag2_storage/qos.cpp, convert<rclcpp::QoS>::encode
QOS_KEYS = ["history", "depth", "reliability", "durability", "deadline", "lifespan", "liveliness",
            "liveliness_lease_duration", "avoid_ros_namespace_conventions"]

#: the bags rosbag2 itself wrote, in ../shared/data/bags (see its README)
ROSBAG2_BAGS = ("rosbag2_pointcloud2_truck", "rosbag2_talker", "rosbag2_split_wbag")


def _rosbag2_bags() -> Path:
    """../shared/data/bags with the three rosbag2-written bags these tests read (skipped where absent, a failure
    in CI: conftest.need_shared)."""
    bags = shared_data() / "bags"
    need_shared(*(bags / b / "metadata.yaml" for b in ROSBAG2_BAGS))
    return bags


def _our_bag(path: Path) -> Path:
    """A rosbag2 directory as our tools write it: settings + cloud (scan_io) and a node output topic."""
    from xmetro_ros.ros.scan_io import write_scans
    from xmetro_ros.scan.geometry import HeadPose
    from xmetro_ros.scan.scan import Scan
    from xmetro_ros.scan.scanner import ScanSettings

    pts = np.arange(30, dtype=np.float64).reshape(10, 3) + 100.0
    head = HeadPose(np.array([0.0, 0.0, 90.0]), np.eye(3))
    scans = [Scan(pts + i, ScanSettings(1000.0, 500.0, 2.0), head, "xm-ls90", {}, "artifact", 1_000_000_000 * (i + 1))
             for i in range(3)]
    write_scans(path, scans)
    return path


def test_metadata_yaml_keys_and_order_are_rosbag2_v9(tmp_path):
    bag = _our_bag(tmp_path / "ours")
    text = (bag / "metadata.yaml").read_text()
    info = yaml.safe_load(text)["rosbag2_bagfile_information"]
    assert list(info) == BAG_KEYS and info["version"] == 9 and info["ros_distro"] == "kilted"
    for t in info["topics_with_message_count"]:
        assert list(t) == ["topic_metadata", "message_count"]
        assert list(t["topic_metadata"]) == TOPIC_KEYS
        qos = t["topic_metadata"]["offered_qos_profiles"]
        assert isinstance(qos, list) and qos, "v9: a YAML sequence (a string is what versions <= 8 wrote)"
        assert all(list(q) == QOS_KEYS for q in qos)
        assert t["topic_metadata"]["type_description_hash"].startswith("RIHS01_")
    assert all(list(f) == FILE_KEYS for f in info["files"])
    assert info["relative_file_paths"] == [f["path"] for f in info["files"]] == ["ours_0.mcap"]
    # yaml-cpp's block style (what rosbag2 writes): sequences indented under their key, "" for empty strings
    assert "  topics_with_message_count:\n    - topic_metadata:\n" in text and 'compression_format: ""' in text


def test_metadata_yaml_matches_the_bags_rosbag2_wrote(tmp_path):
    """Every key of the rosbag2-written metadata.yaml files (versions 4 and 7) is in ours, same kind of value;
    the only differences are the ones version 9 defines (QoS a sequence, ros_distro added)."""
    bags = _rosbag2_bags()
    ours = yaml.safe_load((_our_bag(tmp_path / "ours") / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    seen = 0
    for meta in sorted(bags.glob("*/metadata.yaml")):
        theirs = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
        seen += 1
        assert set(theirs) <= set(ours), (meta, set(theirs) - set(ours))
        for k, v in theirs.items():
            if k == "custom_data":  # map<string,string>; yaml-cpp writes an empty one as ~
                assert v is None or isinstance(v, dict)
                assert isinstance(ours[k], dict)
                continue
            assert type(v) is type(ours[k]), (meta, k)
        for t in theirs["topics_with_message_count"]:
            assert set(t) == set(ours["topics_with_message_count"][0])
            tm = t["topic_metadata"]
            assert set(tm) <= set(TOPIC_KEYS)
            assert isinstance(tm["offered_qos_profiles"], str)  # version < 9: a string ...
            for q in parse_offered_qos(tm["offered_qos_profiles"]):
                assert list(q) == QOS_KEYS  # ... of the same mappings, integer enums
        for f in theirs.get("files", []):
            assert list(f) == FILE_KEYS
    assert seen >= 3


def test_channel_metadata_and_rosbag2_record_match_rosbag2_storage_mcap(tmp_path):
    bags = _rosbag2_bags()
    with open(bags / "rosbag2_pointcloud2_truck" / "outlier.mcap_0.mcap", "rb") as f:
        r = make_reader(f)
        theirs = r.get_summary()
        their_header = r.get_header()
    bag = _our_bag(tmp_path / "ours")
    with open(bag / "ours_0.mcap", "rb") as f:
        r = make_reader(f)
        ours = r.get_summary()
        header = r.get_header()
        records = [m for m in r.iter_metadata() if m.name == "rosbag2"]
    assert header.profile == their_header.profile == "ros2"
    their_keys = {frozenset(c.metadata) for c in theirs.channels.values()}
    assert their_keys == {frozenset({"offered_qos_profiles", "topic_type_hash"})}
    for ch in ours.channels.values():
        assert set(ch.metadata) == {"offered_qos_profiles", "topic_type_hash"} and ch.message_encoding == "cdr"
        assert ours.schemas[ch.schema_id].encoding == "ros2msg"
        profiles = yaml.safe_load(ch.metadata["offered_qos_profiles"])
        assert isinstance(profiles, list) and all(list(p) == QOS_KEYS for p in profiles)
    # update_metadata: {serialized_metadata: the bare BagMetadata}, written when the file opens and when it closes
    assert len(records) == 2 and all(set(m.metadata) == {"serialized_metadata"} for m in records)
    first, last = (yaml.safe_load(m.metadata["serialized_metadata"]) for m in records)
    assert list(last) == BAG_KEYS and last["version"] == 9 and last["message_count"] == 6
    assert first["message_count"] == 0


def test_rosbags_reads_our_qos_and_metadata(tmp_path):
    from rosbags.rosbag2 import Reader
    from rosbags.rosbag2.metadata import dump_qos_v9, parse_qos
    from rosbags.rosbag2.storage_mcap import McapReader

    bag = _our_bag(tmp_path / "ours")
    with Reader(bag) as r:
        qos = {c.topic: dump_qos_v9(c.ext.offered_qos_profiles) for c in r.connections}
        assert r.message_count == 6 and r.ros_distro == "kilted"
    assert qos == {"/scanner_settings": [qos_profiles.SETTINGS], "/scan": [qos_profiles.CLOUD]}
    # The storage-level reader reads the channel metadata string (as ros2 bag play of a bare file does).
    st = McapReader(bag / "ours_0.mcap")
    st.open()
    try:
        chan = {c.topic: dump_qos_v9(c.ext.offered_qos_profiles) for c in st.connections}
    finally:
        st.close()
    assert chan == qos
    # Our v9 string and rosbags' own v9 dump of the same profiles are the same YAML.
    for d in (qos_profiles.SETTINGS, qos_profiles.cloud_output()):
        assert dump_qos_v9(parse_qos(offered_qos_yaml([d]))) == offered_qos_list(offered_qos_yaml([d])) == [d]


def test_older_qos_forms_normalise_as_rosbag2_reads_them():
    """The talker bag's channels (rosbag2 Foxy: integer enums, Foxy 'infinite' 2147483647 s 4294967295 ns) read as
    rosbags reads them; the Foxy infinities become RMW_DURATION_INFINITE as rosbag2's qos.cpp converts them."""
    from rosbags.rosbag2.metadata import dump_qos_v9, parse_qos

    bags = _rosbag2_bags()
    with open(bags / "rosbag2_talker" / "talker.mcap", "rb") as f:
        channels = make_reader(f).get_summary().channels.values()
    for ch in channels:
        text = ch.metadata["offered_qos_profiles"]
        ours = offered_qos_list(text)
        ref = dump_qos_v9(parse_qos(text))
        assert len(ours) == len(ref) == 1
        for k in ("history", "depth", "reliability", "durability", "liveliness", "avoid_ros_namespace_conventions"):
            assert ours[0][k] == ref[0][k], (ch.topic, k)
        assert ours[0]["deadline"] == qos_profiles.INFINITE  # was {2147483647, 4294967295}
        assert ours[0]["history"] == "unknown" and ours[0]["reliability"] == "reliable"
    with pytest.raises(ValueError, match="lacks"):
        offered_qos_list("- history: 1\n  depth: 3")


def test_profiles_are_what_the_graph_reports_for_such_a_publisher():
    """A publisher created with each profile is reported by the ROS graph (what rosbag2's recorder stores) with the
    same policies: the bag records the real offered QoS. And the node's own output publishers (node.output_qos) are
    reported exactly like the profiles our bags record for its outputs. History/depth are not carried by DDS
    discovery (the graph says unknown/0), so they are compared on the profiles themselves."""
    from xmetro_ros.ros.node import output_qos

    cases = {"/fmt/settings": qos_profiles.SETTINGS, "/fmt/cloud": qos_profiles.CLOUD,
             "/fmt/dev": qos_profiles.cloud_output(), "/fmt/quality": qos_profiles.output()}
    node_pubs = {"/fmt/node_dev": (output_qos(2), qos_profiles.cloud_output()),
                 "/fmt/node_quality": (output_qos(), qos_profiles.output())}
    with NodeSpinner(lambda ctx: rclpy.create_node("qos_fmt", context=ctx)) as sp:
        pubs = [sp.node.create_publisher(String, t, as_rclpy(d)) for t, d in cases.items()]
        pubs += [sp.node.create_publisher(String, t, q) for t, (q, _d) in node_pubs.items()]
        assert wait_for(lambda: all(sp.node.get_publishers_info_by_topic(t) for t in [*cases, *node_pubs]), 10.0)
        for t, d in [*cases.items(), *((t, d) for t, (_q, d) in node_pubs.items())]:
            (info,) = sp.node.get_publishers_info_by_topic(t)
            got = qos_to_dict(info.qos_profile)
            for k in QOS_KEYS:
                if k not in ("history", "depth"):
                    assert got[k] == d[k], (t, k, got[k], d[k])
        del pubs
    for q, d in node_pubs.values():
        assert (q.history.name.lower(), q.depth) == (d["history"], d["depth"])


def test_writer_records_given_qos_and_reader_returns_it(tmp_path):
    with BagWriter(tmp_path / "q.mcap") as w:
        w.add_topic("/a", "std_msgs/msg/String", [qos_profiles.SETTINGS])
        w.add_topic("/b", "std_msgs/msg/String")
        w.write("/a", String(data="x"), 1)
    r = BagReader(tmp_path / "q.mcap")
    assert offered_qos_list(r.offered_qos("/a")) == [qos_profiles.SETTINGS]
    assert r.offered_qos("/b") == "[]"  # unknown publishers: an empty sequence, as yaml-cpp dumps one
