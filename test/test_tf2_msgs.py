"""tf2_msgs, the type of /tf and /tf_static: built by setup.py from vendor/tf2_msgs (upstream's definition) where no
tf2_msgs is installed (the pip wheels have none), or the installed one. Either way it must be upstream's type: the
same definition, the same RIHS01 type hash and the same DDS type name, so that real /tf publishers match.
"""

from __future__ import annotations

import json
from pathlib import Path

from geometry_msgs.msg import TransformStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message
from tf2_msgs.msg import TFMessage

from xmetro_ros.bag.schema import msg_file, type_hash
from xmetro_ros.ros.rclpy_util import NodeSpinner, wait_for

ROOT = Path(__file__).resolve().parents[1]
TIMEOUT = 30.0
#: RIHS01 hash of upstream's tf2_msgs/msg/TFMessage (ros2/geometry2), not taken from our own build: what
#: `ros2 topic info -v /tf` prints for robot_state_publisher's /tf and /tf_static on a ROS 2 system, and what rosbag2
#: (Jazzy) records as the topic's type_description_hash, in several independent public projects and logs.
UPSTREAM_TFMESSAGE_HASH = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"
#: tf2_msgs/msg/TF2Error, from the same public lists of golden hashes.
UPSTREAM_TF2ERROR_HASH = "RIHS01_db2485e7d6a0ec75bf087e058ee45df682acc3a621ca7780503d10aac141809a"
#: tf2_ros' StaticTransformBroadcaster QoS (the /tf_static publisher's): reliable, transient local, keep last 1.
STATIC_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: tf2_ros' TransformListener /tf_static QoS: a late subscriber still gets the latched transforms.
LISTENER_STATIC_QOS = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                                 durability=DurabilityPolicy.TRANSIENT_LOCAL)


def _transform(parent: str, child: str, x: float, sec: int) -> TransformStamped:
    t = TransformStamped()
    t.header.frame_id = parent
    t.header.stamp.sec, t.header.stamp.nanosec = sec, 250_000_000
    t.child_frame_id = child
    t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = x, -0.5, 1.25
    t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z, t.transform.rotation.w = 0.0, 0.0, 0.6, 0.8
    return t


def _two_transforms() -> TFMessage:
    return TFMessage(transforms=[_transform("base_link", "tool0", 0.75, 17),
                                 _transform("tool0", "scanner_optical_frame", 0.05, 18)])


def test_definition_is_upstreams():
    """The installed TFMessage.msg is upstream's one line (vendor/tf2_msgs/msg/TFMessage.msg where vendored)."""
    assert msg_file("tf2_msgs/msg/TFMessage").read_text().strip() == "geometry_msgs/TransformStamped[] transforms"
    assert (ROOT / "vendor" / "tf2_msgs" / "msg" / "TFMessage.msg").read_text() == \
        "geometry_msgs/TransformStamped[] transforms\n"
    assert TFMessage.get_fields_and_field_types() == {"transforms": "sequence<geometry_msgs/TransformStamped>"}


def test_serialization_round_trip():
    msg = _two_transforms()
    data = serialize_message(msg)
    back = deserialize_message(data, TFMessage)
    assert back == msg
    assert [t.child_frame_id for t in back.transforms] == ["tool0", "scanner_optical_frame"]
    assert back.transforms[0].header.stamp.sec == 17 and back.transforms[1].transform.translation.x == 0.05
    # CDR: 4-byte encapsulation header, then the sequence length
    assert data[:4] == b"\x00\x01\x00\x00" and int.from_bytes(data[4:8], "little") == 2


def test_type_hash_is_upstreams():
    """The type description the build generated (share/tf2_msgs/msg/TFMessage.json) hashes to upstream's RIHS01, and
    it was built against the installed geometry_msgs (the dependency hash it records is that wheel's own)."""
    assert type_hash("tf2_msgs/msg/TFMessage") == UPSTREAM_TFMESSAGE_HASH
    assert type_hash("tf2_msgs/msg/TF2Error") == UPSTREAM_TF2ERROR_HASH
    desc = json.loads(msg_file("tf2_msgs/msg/TFMessage").with_suffix(".json").read_text())
    hashes = {e["type_name"]: e["hash_string"] for e in desc["type_hashes"]}
    assert hashes["tf2_msgs/msg/TFMessage"] == UPSTREAM_TFMESSAGE_HASH
    assert hashes["geometry_msgs/msg/TransformStamped"] == type_hash("geometry_msgs/msg/TransformStamped")
    assert hashes["std_msgs/msg/Header"] == type_hash("std_msgs/msg/Header")


def test_tf_static_is_latched_for_a_late_subscriber():
    """A /tf_static publisher (transient local, as tf2_ros' static broadcaster) sends two transforms before any
    subscriber exists; a subscription made afterwards in another participant (tf2_ros' listener QoS) still receives
    them, and the graph names the type tf2_msgs/msg/TFMessage with upstream's hash."""
    sent = _two_transforms()
    got: list[TFMessage] = []
    with NodeSpinner(lambda ctx: Node("xmetro_tf_static_pub", context=ctx)) as pub_side:
        pub = pub_side.node.create_publisher(TFMessage, "/tf_static", STATIC_QOS)
        pub.publish(sent)
        with NodeSpinner(lambda ctx: Node("xmetro_tf_static_sub", context=ctx)) as sub_side:
            sub_side.node.create_subscription(TFMessage, "/tf_static", got.append, LISTENER_STATIC_QOS)
            assert wait_for(lambda: len(got) >= 1, TIMEOUT), "the latched /tf_static message never arrived"
            assert got[0] == sent
            assert [t.child_frame_id for t in got[0].transforms] == ["tool0", "scanner_optical_frame"]
            assert wait_for(lambda: len(sub_side.node.get_publishers_info_by_topic("/tf_static")) == 1, TIMEOUT)
            (info,) = sub_side.node.get_publishers_info_by_topic("/tf_static")
            assert info.topic_type == "tf2_msgs/msg/TFMessage"
            assert str(info.topic_type_hash) == UPSTREAM_TFMESSAGE_HASH
            assert info.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL


def test_tf_stream_between_participants():
    """/tf (volatile, as tf2_ros' TransformBroadcaster): messages published once the subscription is matched arrive
    in order and intact."""
    got: list[TFMessage] = []
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    with NodeSpinner(lambda ctx: Node("xmetro_tf_sub", context=ctx)) as sub_side, \
            NodeSpinner(lambda ctx: Node("xmetro_tf_pub", context=ctx)) as pub_side:
        sub_side.node.create_subscription(TFMessage, "/tf", got.append, qos)
        pub = pub_side.node.create_publisher(TFMessage, "/tf", qos)
        assert wait_for(lambda: pub.get_subscription_count() == 1, TIMEOUT)
        for i in range(5):
            pub.publish(TFMessage(transforms=[_transform("world", "base_link", float(i), 100 + i)]))
        assert wait_for(lambda: len(got) >= 5, TIMEOUT)
        assert [m.transforms[0].transform.translation.x for m in got] == [0.0, 1.0, 2.0, 3.0, 4.0]
