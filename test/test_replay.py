"""xmetro replay: the shipped bags through a live xmetro_node (in this process, own DDS context) against the goldens;
bags written by others (the C++ rosbag2's truck clouds: no settings); truncated, empty and scan-less bags."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from conftest import need_shared

from xmetro_ros.apps.replay import ReplayError, replay_bag
from xmetro_ros.bag.reader import BagFormatError, BagReader
from xmetro_ros.msg import ScanQuality
from xmetro_ros.ros.node_outputs import Tolerance, compare_outputs, read_outputs
from xmetro_ros.ros.rclpy_util import NodeSpinner

ROOT = Path(__file__).resolve().parents[1]
BAGS = ROOT / "bags"
TRUCK = ROOT.parent / "shared" / "data" / "bags" / "rosbag2_pointcloud2_truck"


@pytest.fixture(scope="module")
def live_node():
    """xmetro_node with its default parameters and the shipped default model, spinning in this process."""
    from xmetro_ros.ros.node import XmetroNode

    with NodeSpinner(lambda ctx: XmetroNode(context=ctx)) as sp:
        assert sp.node.core.model is not None, sp.node.core.degraded
        yield sp.node


def test_regression_bag_through_live_node_matches_golden(live_node, tmp_path):
    golden = json.loads((BAGS / "golden" / "golden.json").read_text())
    assert golden["model_id"] == live_node.core.model_id, (
        "goldens were made with another model: regenerate them with `python tools/make_bags.py --golden-only`")
    import hashlib

    bag = BAGS / "regression.mcap"
    assert hashlib.sha256(bag.read_bytes()).hexdigest() == golden["bags"]["regression"]["input_sha256"]
    rec = tmp_path / "live.mcap"
    res = replay_bag(bag, fast=True, record=rec)
    assert res.complete and res.scans_sent == len(golden["bags"]["regression"]["scans"]) == 4
    assert res.settings_sent == 4 and res.defaulted == 0 and not res.losses and not res.notes, res.notes
    live = read_outputs(rec)
    ref = read_outputs(BAGS / "golden" / "regression.mcap")
    assert all(o.deviations is not None and o.corrected is not None for o in live)
    diffs = compare_outputs(live, ref, Tolerance.from_dict(golden["tolerance"]), clouds=("deviations",))
    assert not diffs, ("live outputs differ from bags/golden beyond the stated tolerance (if the processing changed "
                       "on purpose: `python tools/make_bags.py --golden-only`, then review golden.json):\n"
                       + "\n".join(diffs[:20]))
    # The recording also holds what was replayed, message for message.
    topics = BagReader(rec).topics()
    assert {"/scan", "/scanner_settings", "/xmetro_node/quality", "/xmetro_node/deviations"} <= set(topics)


def test_rate_mode_replays_every_scan(live_node):
    # Scans are 2 s apart in the bag: at rate 20 every 0.1 s; the node's queue (4) holds them all.
    res = replay_bag(BAGS / "demo.mcap", rate=20.0)
    assert res.complete and res.scans_sent == 4 and res.mode == "rate 20"
    assert [s.stamp_ns for s in res.scans] == sorted(s.stamp_ns for s in res.scans)
    assert all(int(s.quality.error_code) == 0 and not s.quality.settings_defaulted for s in res.scans)


def test_truck_bag_from_cpp_rosbag2_replays_with_defaulted_settings(live_node):
    need_shared(TRUCK)
    res = replay_bag(TRUCK, fast=True)
    assert res.scans_sent == 3 and res.complete and res.settings_sent == 0
    assert [s.topic for s in res.scans] == ["cloud_1", "cloud_2", "cloud_3"]
    assert [s.points for s in res.scans] == [80256, 35200, 80256]
    assert res.defaulted == 3
    for s in res.scans:
        # A street scene in metres (a vehicle's lidar) is no laser line scan: refused whole, with its own code.
        q = s.quality
        assert q.header.frame_id == "test" and int(q.error_code) == ScanQuality.ERROR_NOT_A_LASER_SCAN
        assert q.verdict == ScanQuality.VERDICT_ERROR and q.settings_defaulted
        assert "not a laser line scan" in q.message
    summary = res.summary()
    assert "no xmetro_ros/msg/ScannerSettings messages" in summary and "settings DEFAULTED" in summary


def test_truncated_bag_replays_every_complete_message(live_node, tmp_path):
    src = BAGS / "demo.mcap"
    cut = tmp_path / "cut.mcap"
    data = src.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.7)])
    complete = [m for m in BagReader(cut).messages() if m.topic == "/scan"]
    assert 0 < len(complete) < 4
    res = replay_bag(cut, fast=True)
    assert res.scans_sent == len(complete) and res.complete
    assert res.losses, "the truncation must be reported"
    assert any("not closed" in x or "damaged" in x for x in res.losses)
    assert "LOSS:" in res.summary()


def test_empty_and_scanless_bags_are_refused_clearly(tmp_path):
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(BagFormatError, match="empty"):
        replay_bag(empty, fast=True)
    with pytest.raises(FileNotFoundError):
        replay_bag(tmp_path / "missing.mcap")
    talker = need_shared(ROOT.parent / "shared" / "data" / "bags" / "rosbag2_talker")
    with pytest.raises(ReplayError, match="no sensor_msgs/msg/PointCloud2 input topic"):
        replay_bag(talker, fast=True)
    with pytest.raises(ReplayError, match="not in the bag"):
        replay_bag(BAGS / "demo.mcap", topics=["/nope"])


def test_replay_without_node_fails_with_reason(tmp_path):
    bag = tmp_path / "demo.mcap"
    shutil.copy(BAGS / "demo.mcap", bag)
    with pytest.raises(ReplayError, match="no node subscribing"):
        replay_bag(bag, fast=True, node_name="no_such_node", scan_topic="/no_such_scan", discovery_timeout=1.0)


def test_replay_starts_over_with_a_new_participant_and_says_what_it_saw(tmp_path):
    """Not found within ``rediscover_after``: the replay tries once more with a new DDS participant (other
    ports, a new identity) and finds a node that came up meanwhile; never found, the error lists what it saw."""
    import threading

    from rclpy.node import Node
    from sensor_msgs.msg import PointCloud2

    from xmetro_ros.apps.replay import _Replayer

    def late_node(ctx):
        n = Node("late_node", context=ctx)
        n.create_subscription(PointCloud2, "/late_scan", lambda _m: None, 10)
        n.create_publisher(ScanQuality, "/late_node/quality", 10)
        return n

    lines: list[str] = []
    rep = _Replayer("late_node", "/late_scan", "/late_settings", None, lines.append)
    first = rep.node
    holder: dict = {}
    timer = threading.Timer(2.5, lambda: holder.setdefault("sp", NodeSpinner(late_node)))
    timer.start()
    try:
        rep.connect(30.0, need_settings=False, rediscover_after=1.0)
        assert rep.node is not first and any("new DDS participant" in x for x in lines), lines
        assert rep.pub_scan.get_subscription_count() == 1
    finally:
        timer.join()
        rep.close()
        holder["sp"].close()
    gone = _Replayer("gone_node", "/gone_scan", "/gone_settings", None, lines.append)
    try:
        with pytest.raises(ReplayError, match=r"seen: 0 subscription\(s\) of /gone_scan, 0 publisher\(s\) of "
                                              r"/gone_node/quality, nodes: "):
            gone.connect(1.5, need_settings=False, rediscover_after=0.5)
    finally:
        gone.close()


def test_cli_replay_prints_summary(live_node, capsys):
    need_shared(TRUCK)
    import argparse

    from xmetro_ros.apps.replay import register, run

    p = argparse.ArgumentParser()
    register(p.add_subparsers())
    args = p.parse_args(["replay", str(TRUCK), "--fast", "--topic", "cloud_2"])
    assert run(args) == 0
    out = capsys.readouterr().out
    assert "1 scans" in out and "cloud_2" in out and "defaulted" in out


def test_unknown_message_types_are_skipped_and_listed(live_node, tmp_path):
    """A bag that also holds a topic of a type not installed here (and a known type that is neither scan nor
    settings): the scans and settings are replayed, and both other topics are skipped with their types listed in
    the summary."""
    from mcap.writer import CompressionType, Writer

    from xmetro_ros.bag import schema

    src = BagReader(BAGS / "demo.mcap")
    types = src.topics()
    msgs = [m for m in src.messages(deserialize=False) if m.topic in ("/scan", "/scanner_settings")][:4]
    assert {m.topic for m in msgs} == {"/scan", "/scanner_settings"}
    p = tmp_path / "mixed.mcap"
    with open(p, "wb") as f:
        w = Writer(f, compression=CompressionType.NONE)
        w.start(profile="ros2", library="test")
        ch = {}
        for topic in ("/scan", "/scanner_settings"):
            sid = w.register_schema(types[topic], "ros2msg", schema.schema_text(types[topic]).encode())
            ch[topic] = w.register_channel(topic, "cdr", sid)
        sw = w.register_schema("acme_msgs/msg/Widget", "ros2msg", b"int32 a\n")
        ch["/widget"] = w.register_channel("/widget", "cdr", sw)
        ss = w.register_schema("std_msgs/msg/String", "ros2msg", schema.schema_text("std_msgs/msg/String").encode())
        ch["/chatter"] = w.register_channel("/chatter", "cdr", ss)
        for m in msgs:
            w.add_message(ch[m.topic], m.log_time_ns, bytes(m.raw), m.log_time_ns)
            w.add_message(ch["/widget"], m.log_time_ns, b"\x00\x01\x00\x00\x07\x00\x00\x00", m.log_time_ns)
            w.add_message(ch["/chatter"], m.log_time_ns, b"\x00\x01\x00\x00\x02\x00\x00\x00a\x00", m.log_time_ns)
        w.finish()
    res = replay_bag(p, fast=True)
    n_scans = sum(m.topic == "/scan" for m in msgs)
    assert res.complete and res.scans_sent == n_scans and all(s.quality is not None for s in res.scans)
    assert res.skipped == {"/widget": "acme_msgs/msg/Widget", "/chatter": "std_msgs/msg/String"}
    text = res.summary()
    assert "/widget [acme_msgs/msg/Widget]" in text and "/chatter [std_msgs/msg/String]" in text
