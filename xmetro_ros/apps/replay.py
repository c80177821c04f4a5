"""`xmetro replay BAG`: publish a bag's scans and settings into a running xmetro_node and record its outputs.

Which messages are replayed:
- every ``xmetro_ros/msg/ScannerSettings`` message → the node's ``scanner_settings`` topic;
- every ``sensor_msgs/msg/PointCloud2`` message of the input topics → the node's ``scan`` topic. Input topics
  default to all PointCloud2 topics of the bag except the node's own outputs (``*/deviations``, ``*/corrected``),
  so a bag written by other tools (e.g. rosbag2's ``cloud_1``, ``cloud_2``, ...) replays as is; ``--topic`` picks.
- anything else is not replayed (the report lists those topics).

Timing: the original log-time spacing divided by ``--rate`` (default 1), or ``--fast``: as fast as the node keeps
up, without dropping: the next scan is sent only once the node's ``~/quality`` for the previous one has arrived.
Settings are sent before the scans they precede in the bag and are acknowledged by the node's reader before the
next scan goes out (so the node cannot see a scan before the settings stamped for it).

``--record OUT.mcap`` writes what was replayed (``/scan``, ``/scanner_settings``) and what the node published in
answer (``~/quality``, ``~/deviations``, ``~/corrected``, ``/diagnostics``) with BAG's :class:`BagWriter`,
log time = receive time.

Bags without settings (e.g. clouds recorded by other tools): the node then applies its configured default settings
and says so in ``ScanQuality.settings_defaulted`` / ``message``; the replay report says it too. Truncated bags:
BAG's reader reports what it could not read; every complete message is replayed and the losses are reported.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..judge.flags import verdict_name
from ..ros.convert import stamp_to_ns
from ..ros.node_outputs import (
    DIAGNOSTICS_TYPE,
    POINTCLOUD2,
    QUALITY_TYPE,
    SETTINGS_TYPE,
    TopicError,
    cdr_header,
    classify_topics,
    describe_loss,
)

if TYPE_CHECKING:
    from ..bag.writer import BagWriter

__all__ = ["ReplayError", "ReplayResult", "ScanOutcome", "register", "replay_bag", "run"]

#: Seconds after which a replay that has not found its node starts over with a new DDS participant (once).
REDISCOVER_S = 10.0


class ReplayError(RuntimeError):
    """The bag cannot be replayed (no scans, node not found, node not answering)."""


@dataclass
class ScanOutcome:
    """One replayed scan and the node's ScanQuality for it (None when none came back in time)."""

    index: int
    topic: str
    stamp_ns: int
    frame_id: str
    points: int
    quality: Any | None = None
    settings_stamp_ns: int | None = None  # stamp of the last settings sent before this scan (None: none sent)

    @property
    def verdict(self) -> str:
        return "NO ANSWER" if self.quality is None else verdict_name(int(self.quality.verdict))

    def line(self) -> str:
        """One summary line: index, topic, stamp, points, verdict, predicted mean |error| (mm), message."""
        head = f"#{self.index:<3d} {self.topic:<20s} stamp={self.stamp_ns / 1e9:.3f}s frame={self.frame_id!r} " \
               f"points={self.points}"
        q = self.quality
        if q is None:
            return f"{head} -> NO QUALITY RECEIVED"
        mae = ", ".join(f"{v * 1e6:.1f}" for v in q.mean_abs_error)  # m on the topic, µm for a reader
        dflt = " settings DEFAULTED" if q.settings_defaulted else ""
        err = f" error_code={int(q.error_code)}" if int(q.error_code) else ""
        msg = f" — {q.message}" if q.message else ""
        return (f"{head} -> {self.verdict}{err} valid={q.points_valid} usable={q.usable_fraction:.3f} "
                f"mean|e|(x,y,z)=({mae}) µm{dflt}{msg}")


@dataclass
class ReplayResult:
    """What a replay did: what was sent, what came back, what was defaulted or lost."""

    bag: str
    mode: str
    scans: list[ScanOutcome] = field(default_factory=list)
    settings_sent: int = 0
    skipped: dict[str, str] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    losses: list[str] = field(default_factory=list)
    recorded: Path | None = None
    wall_s: float = 0.0
    bytes_sent: int = 0
    diagnostics_errors: list[str] = field(default_factory=list)

    @property
    def scans_sent(self) -> int:
        return len(self.scans)

    @property
    def answered(self) -> int:
        return sum(1 for s in self.scans if s.quality is not None)

    @property
    def defaulted(self) -> int:
        return sum(1 for s in self.scans if s.quality is not None and s.quality.settings_defaulted)

    @property
    def complete(self) -> bool:
        return self.answered == self.scans_sent

    def summary(self) -> str:
        rate = self.scans_sent / self.wall_s if self.wall_s > 0 else 0.0
        lines = [f"replay {self.bag} ({self.mode}): {self.scans_sent} scans, {self.settings_sent} settings sent, "
                 f"{self.answered} qualities received, {self.defaulted} with defaulted settings, "
                 f"{self.wall_s:.2f} s ({rate:.2f} scans/s, {self.bytes_sent / 1e6:.1f} MB)"]
        lines += [s.line() for s in self.scans]
        if self.skipped:
            lines.append("not replayed: " + ", ".join(f"{t} [{ty}]" for t, ty in sorted(self.skipped.items())))
        lines += [f"note: {n}" for n in self.notes]
        lines += [f"LOSS: {x}" for x in self.losses]
        lines += [f"diagnostics ERROR: {x}" for x in self.diagnostics_errors]
        if self.recorded is not None:
            lines.append(f"recorded: {self.recorded}")
        return "\n".join(lines)


def _header_of(msg: Any) -> tuple[int, str]:
    h = getattr(msg, "header", None)
    if h is None:
        return 0, ""
    return stamp_to_ns(h.stamp), str(h.frame_id)


def _qos_like(infos: list[Any], depth: int) -> Any:
    """A subscription QoS compatible with every discovered publisher (reliable only if all are reliable)."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    reliable = bool(infos) and all(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE for i in infos)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.VOLATILE)


class _Replayer:
    """The replay's own rclpy node: publishers into the target node, subscriptions to its outputs, recorder."""

    def __init__(self, node_name: str, scan_topic: str, settings_topic: str, record: Path | None,
                 log: Callable[[str], None]) -> None:
        from rclpy.node import Node

        from ..ros.rclpy_util import NodeSpinner

        self.node_name = node_name.strip("/")
        self.scan_topic = scan_topic
        self.settings_topic = settings_topic
        self.out = {k: f"/{self.node_name}/{k}" for k in ("quality", "deviations", "corrected")}
        self.out["diagnostics"] = "/diagnostics"
        self.log = log
        self.lock = threading.Lock()
        self.cond = threading.Condition(self.lock)
        self.qualities: list[Any] = []
        self.counts = {k: 0 for k in self.out}
        self.diag_errors: list[str] = []
        self.writer: BagWriter | None = None
        self.record = record
        self._make_node = lambda ctx: Node("xmetro_replay", context=ctx)
        self.spinner = NodeSpinner(self._make_node)
        self.node = self.spinner.node
        self.pub_scan: Any = None
        self.pub_settings: Any = None
        self.subs: list[Any] = []

    # -- set-up --------------------------------------------------------------------------------------------------
    def connect(self, timeout: float, need_settings: bool, rediscover_after: float = REDISCOVER_S) -> None:
        """Wait for the target node (after ``rediscover_after`` s without it, once more with a new participant),
        create matching publishers/subscriptions, wait until they are matched."""
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
        from rclpy.serialization import deserialize_message
        from sensor_msgs.msg import PointCloud2

        from ..msg import ScannerSettings, ScanQuality
        from ..ros.rclpy_util import wait_for

        deadline = time.monotonic() + timeout

        def left() -> float:
            return max(0.1, deadline - time.monotonic())

        def found() -> bool:
            return (self.node.count_subscribers(self.scan_topic) > 0
                    and self.node.count_publishers(self.out["quality"]) > 0)

        # Not found in time: once, a new participant (other ports, a new identity) takes over. In CI a replay created
        # right after another in the same process once saw nothing of a live node there for its whole 30 s (cause
        # not found; 0 of 132 such replays failed here, 92 of them under load), while the node itself was running.
        if not wait_for(found, timeout=min(rediscover_after, left())) and time.monotonic() < deadline:
            self.log(f"replay: {self.node_name} not found after {rediscover_after:g} s; "
                     "trying again with a new DDS participant")
            self._new_participant()
            wait_for(found, timeout=left())
        node = self.node
        if not found():
            raise ReplayError(f"no node subscribing to {self.scan_topic} and publishing {self.out['quality']} "
                              f"found within {timeout:g} s (is xmetro_node running, with the same ROS_DOMAIN_ID?); "
                              f"{self._graph_summary()}")
        # Inputs: reliable + transient-local publishers match any subscriber QoS.
        pub_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        # Outputs: QoS like the node's publishers; everything recorded as serialized bytes, each topic with the QoS
        # its publishers really offer (ours for the inputs, the node's as the graph reports them for the outputs).
        out_types = {"quality": QUALITY_TYPE, "deviations": POINTCLOUD2, "corrected": POINTCLOUD2,
                     "diagnostics": DIAGNOSTICS_TYPE}
        if self.record is not None:
            from ..bag.writer import BagWriter

            self.writer = BagWriter(self.record, compression="zstd")
            self.writer.add_topic(self.scan_topic, POINTCLOUD2, [pub_qos])
            self.writer.add_topic(self.settings_topic, SETTINGS_TYPE, [pub_qos])
        wait_for(lambda: all(node.count_publishers(self.out[k]) > 0 for k in ("deviations", "corrected")),
                 timeout=min(5.0, left()))
        types = {"quality": ScanQuality, "deviations": PointCloud2, "corrected": PointCloud2,
                 "diagnostics": DiagnosticArray}
        for key, topic in self.out.items():
            infos = node.get_publishers_info_by_topic(topic)
            if key != "diagnostics" and not infos:
                self.log(f"replay: node publishes no {topic}: not recorded")
                continue
            qos = _qos_like(infos, depth=1000 if key == "quality" else 200)
            if self.writer is not None:
                from ..bag import qos_profiles

                # No publisher seen yet (only /diagnostics gets here): the node's documented output profile.
                offered = [i.qos_profile for i in infos] or [qos_profiles.output()]
                self.writer.add_topic(topic, out_types[key], offered)

            def cb(raw: bytes, key: str = key, topic: str = topic, mtype: Any = types[key]) -> None:
                self._on_output(key, topic, raw, mtype, deserialize_message)

            self.subs.append(node.create_subscription(types[key], topic, cb, qos, raw=True))
        self.pub_scan = node.create_publisher(PointCloud2, self.scan_topic, pub_qos)
        self.pub_settings = node.create_publisher(ScannerSettings, self.settings_topic, pub_qos)
        quality_sub = next((x for x in self.subs if x.topic_name == self.out["quality"]), None)
        ok = wait_for(
            lambda: self.pub_scan.get_subscription_count() > 0
            and (not need_settings or self.pub_settings.get_subscription_count() > 0)
            and (quality_sub is None or quality_sub.get_publisher_count() > 0),
            timeout=left(),
        )
        if not ok:
            raise ReplayError(f"publishers/subscriptions to {self.node_name} not matched within {timeout:g} s")
        # Matching is reported per side: the node's writers must also have matched our readers, or the first
        # answers are lost. Our readers were announced in creation order (quality first, diagnostics last) on DDS's
        # reliable discovery channel, so a first /diagnostics message (the node publishes it every
        # diagnostics_period) proves the node has matched the quality reader too. Without one, a fixed margin.
        if not wait_for(lambda: self.counts["diagnostics"] > 0, timeout=min(3.0, left())):
            time.sleep(0.5)

    def _new_participant(self) -> None:
        """Replace the replay's node by one in a new context (a new DDS participant), made before the old one is
        closed so that it gets other ports. Only before any publisher or subscription exists."""
        from ..ros.rclpy_util import NodeSpinner

        old = self.spinner
        self.spinner = NodeSpinner(self._make_node)
        self.node = self.spinner.node
        old.close()

    def _graph_summary(self) -> str:
        """What this participant sees of the graph (for the not-found error): the counts waited for and the nodes."""
        from ..ros.rclpy_util import other_nodes

        names = other_nodes(self.node)
        return (f"seen: {self.node.count_subscribers(self.scan_topic)} subscription(s) of {self.scan_topic}, "
                f"{self.node.count_publishers(self.out['quality'])} publisher(s) of {self.out['quality']}, "
                f"nodes: {', '.join(names) if names else 'none'}")

    def _on_output(self, key: str, topic: str, raw: bytes, mtype: Any, deserialize: Callable) -> None:
        msg = deserialize(raw, mtype) if key in ("quality", "diagnostics") else None
        with self.cond:
            if self.writer is not None:
                self.writer.write(topic, raw, time.time_ns())
            self.counts[key] += 1
            if key == "quality":
                self.qualities.append(msg)
            elif key == "diagnostics" and msg is not None:
                for st in msg.status:
                    if st.level == b"\x02" or st.level == 2:
                        self.diag_errors.append(f"{st.name}: {st.message}")
            self.cond.notify_all()

    # -- sending -------------------------------------------------------------------------------------------------
    def send(self, kind: str, raw: bytes) -> None:
        pub = self.pub_scan if kind == "scan" else self.pub_settings
        topic = self.scan_topic if kind == "scan" else self.settings_topic
        with self.lock:
            if self.writer is not None:
                self.writer.write(topic, raw, time.time_ns())
        pub.publish(raw)
        if kind == "settings":
            # The node must hold these settings before the next scan arrives (it picks, per scan, the latest
            # settings stamped at or before the scan): wait for the DDS acknowledgement, then let its executor
            # take the message.
            from rclpy.duration import Duration

            pub.wait_for_all_acked(Duration(seconds=10))
            time.sleep(0.1)

    def wait_qualities(self, n: int, timeout: float) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: len(self.qualities) >= n, timeout=timeout)

    def wait_outputs(self, n_ok: int, timeout: float) -> None:
        keys = [k for k in ("deviations", "corrected") if any(s.topic_name == self.out[k] for s in self.subs)]
        with self.cond:
            self.cond.wait_for(lambda: all(self.counts[k] >= n_ok for k in keys), timeout=timeout)

    def close(self) -> None:
        try:
            self.spinner.close()
        finally:
            if self.writer is not None:
                with self.lock:
                    self.writer.close()


def replay_bag(
    bag: str | Path,
    *,
    rate: float = 1.0,
    fast: bool = False,
    record: str | Path | None = None,
    node_name: str = "xmetro_node",
    scan_topic: str = "/scan",
    settings_topic: str = "/scanner_settings",
    topics: list[str] | None = None,
    discovery_timeout: float = 30.0,
    answer_timeout: float = 60.0,
    log: Callable[[str], None] = lambda s: None,
    rediscover_after: float = REDISCOVER_S,
) -> ReplayResult:
    """Replay ``bag`` into the running node ``node_name`` and return what happened.

    Args:
        bag: a bare .mcap file or a rosbag2 directory (metadata.yaml, possibly split files).
        rate: time scale of the original log-time spacing (2 = twice as fast); ignored with ``fast``.
        fast: send each scan as soon as the node's ScanQuality for the previous one arrived (no drops).
        record: write inputs and the node's outputs to this .mcap.
        node_name: the target node's name (its outputs are ``/<node_name>/quality`` ...).
        topics: PointCloud2 topics of the bag to replay (default: all but node outputs).
        discovery_timeout: seconds to find and match the node.
        rediscover_after: seconds after which, the node not yet found, the replay starts over once with a new DDS
            participant (within ``discovery_timeout``).
        answer_timeout: seconds to wait for one scan's ScanQuality (fast mode), or for the stragglers at the end.
        log: progress lines (one per scan).

    Raises:
        ReplayError: no scans in the bag, node not found, or bad arguments.
        FileNotFoundError: the bag does not exist.
    """
    from ..bag.reader import BagReader

    if not fast and not rate > 0:
        raise ReplayError(f"--rate must be > 0, got {rate}")
    bag = Path(bag)
    if not bag.exists():
        raise FileNotFoundError(f"bag {bag} does not exist")
    if record is not None and Path(record).exists():
        raise FileExistsError(f"record output {record} already exists")
    reader = BagReader(bag)
    bag_topics = dict(reader.topics())
    try:
        scan_topics, settings_topics = classify_topics(bag_topics, topics)
    except TopicError as e:
        raise ReplayError(str(e)) from e
    if not scan_topics:
        raise ReplayError(f"bag {bag} has no {POINTCLOUD2} input topic to replay (topics: "
                          + (", ".join(f"{t} [{ty}]" for t, ty in sorted(bag_topics.items())) or "none") + ")")
    result = ReplayResult(bag=str(bag), mode="fast" if fast else f"rate {rate:g}",
                          recorded=Path(record) if record is not None else None)
    if not settings_topics:
        result.notes.append(f"the bag has no {SETTINGS_TYPE} messages: the node applies its configured default "
                            "settings (and default head pose) to every scan; ScanQuality.settings_defaulted says so")
    if len(scan_topics) > 1:
        result.notes.append(f"{len(scan_topics)} PointCloud2 topics ({', '.join(scan_topics)}) all replayed "
                            f"into {scan_topic}, in the order of the bag")
    result.skipped = {t: ty for t, ty in bag_topics.items() if t not in set(scan_topics) | set(settings_topics)}
    rep = _Replayer(node_name, scan_topic, settings_topic, result.recorded, log)
    t_start = time.monotonic()
    try:
        rep.connect(discovery_timeout, need_settings=bool(settings_topics), rediscover_after=rediscover_after)
        wanted = set(scan_topics) | set(settings_topics)
        t0_bag: int | None = None
        last_settings: int | None = None
        t0_wall = time.monotonic()
        for m in reader.messages(topics=wanted, deserialize=False):
            if not fast:
                if t0_bag is None:
                    t0_bag = m.log_time_ns
                delay = t0_wall + (m.log_time_ns - t0_bag) / 1e9 / rate - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            raw = bytes(m.raw)
            result.bytes_sent += len(raw)
            if m.topic in settings_topics:
                rep.send("settings", raw)
                result.settings_sent += 1
                last_settings = cdr_header(raw)[0]
                continue
            stamp, frame, n = cdr_header(raw, cloud=True)
            outcome = ScanOutcome(len(result.scans), m.topic, stamp, frame, n, settings_stamp_ns=last_settings)
            result.scans.append(outcome)
            rep.send("scan", raw)
            if fast:
                if not rep.wait_qualities(len(result.scans), answer_timeout):
                    raise ReplayError(f"no ~/quality from {node_name} for scan #{outcome.index} within "
                                      f"{answer_timeout:g} s")
                outcome.quality = rep.qualities[outcome.index]
                log(outcome.line())
        rep.wait_qualities(len(result.scans), answer_timeout)
        n_ok = 0
        for i, s in enumerate(result.scans):
            if s.quality is None and i < len(rep.qualities):
                s.quality = rep.qualities[i]
                log(s.line())
            if s.quality is not None and int(s.quality.error_code) == 0:
                n_ok += 1
        # Deviations / corrected are published with (before) the quality; wait for stragglers of the recording.
        rep.wait_outputs(n_ok, timeout=5.0)
        result.diagnostics_errors = list(dict.fromkeys(rep.diag_errors))
    finally:
        rep.close()
        result.wall_s = time.monotonic() - t_start
    if len(rep.qualities) > len(result.scans):
        result.notes.append(f"{len(rep.qualities) - len(result.scans)} extra ScanQuality messages received "
                            "(another publisher on the scan topic?)")
    for s in result.scans:
        q = s.quality
        if q is None:
            continue
        if s.stamp_ns and _header_of(q)[0] != s.stamp_ns:
            result.notes.append(f"scan #{s.index}: quality stamp differs from the scan's (paired by order)")
        # The node must have used the settings sent just before the scan when they are stamped at or before it.
        if s.settings_stamp_ns is not None and s.settings_stamp_ns <= s.stamp_ns and (
                q.settings_defaulted or _header_of(q.settings)[0] != s.settings_stamp_ns):
            result.notes.append(f"scan #{s.index}: judged with settings stamped {_header_of(q.settings)[0]} ns "
                                f"(defaulted: {q.settings_defaulted}), not those sent before it "
                                f"({s.settings_stamp_ns} ns)")
    result.losses = describe_loss(getattr(reader, "report", None))
    if not result.complete:
        result.notes.append(f"{result.scans_sent - result.answered} scans got no ScanQuality within "
                            f"{answer_timeout:g} s (dropped by the node's queue? use --fast)")
    return result


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``xmetro replay`` to the ``xmetro`` sub-commands."""
    p = subparsers.add_parser("replay", help="replay a bag's scans and settings into a running xmetro_node",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bag", help="a .mcap file or a rosbag2 directory")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--rate", type=float, default=1.0, help="time scale of the original timing (default 1)")
    g.add_argument("--fast", action="store_true", help="as fast as the node keeps up, waiting for each ~/quality")
    p.add_argument("--record", metavar="OUT.mcap", help="record inputs and the node's outputs to this MCAP")
    p.add_argument("--node", default="xmetro_node", help="name of the target node (default xmetro_node)")
    p.add_argument("--topic", action="append", help="PointCloud2 topic of the bag to replay (repeatable)")
    p.add_argument("--timeout", type=float, default=60.0, help="seconds to wait for the node / for answers")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """``xmetro replay``: replay the bag into the running node and print the summary; returns the exit code."""
    try:
        res = replay_bag(args.bag, rate=args.rate, fast=args.fast, record=args.record, node_name=args.node,
                         topics=args.topic, discovery_timeout=args.timeout, answer_timeout=args.timeout,
                         log=lambda s: print(s, flush=True))
    except (ReplayError, OSError, ValueError) as e:
        print(f"xmetro replay: error: {e}", file=sys.stderr)
        return 1
    print(res.summary())
    return 0 if res.complete else 1
