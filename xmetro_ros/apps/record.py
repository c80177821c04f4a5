"""``xmetro record -o OUT [TOPIC ...]``: record ROS 2 topics to an MCAP bag in rosbag2's format;
``xmetro bag recover IN OUT``: make a killed recording complete (summary, index, metadata.yaml) for every reader.

Stops on SIGINT or SIGTERM (or after ``--duration`` seconds), closes the bag with a complete summary and prints
what was recorded. A bag killed with SIGKILL keeps every completed chunk readable (``--chunk-size`` bounds what
can be lost); ``xmetro bag recover`` then makes it a complete bag (summary, index, metadata.yaml) for every reader.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
import time
from typing import Any

__all__ = ["register", "run", "run_recover"]


def register(subparsers: Any) -> None:
    """Add ``xmetro record`` to the ``xmetro`` sub-commands."""
    p = subparsers.add_parser("record", help="record ROS 2 topics to MCAP (rosbag2 format)", description=__doc__)
    p.add_argument("topics", nargs="*", metavar="TOPIC", help="topics to record (default: all, discovered "
                   "periodically)")
    p.add_argument("-o", "--output", required=True,
                   help="OUT.mcap for one bare file, or a directory name for a rosbag2 directory (needed to split)")
    p.add_argument("--compression", choices=["none", "zstd"], default="none", help="MCAP chunk compression")
    p.add_argument("--chunk-size", type=int, default=1024 * 1024, help="bytes per chunk (default 1 MiB)")
    p.add_argument("--split-size", type=float, default=None, help="start a new file after this many MB")
    p.add_argument("--split-duration", type=float, default=None, help="start a new file after this many s")
    p.add_argument("--discovery-period", type=float, default=1.0, help="seconds between topic discovery scans")
    p.add_argument("--qos-depth", type=int, default=100, help="subscription queue depth")
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds")
    p.add_argument("--progress", type=float, default=0.0,
                   help="print per-topic counts every this many seconds (0: off)")
    p.add_argument("--exclude", action="append", default=[], help="topic never recorded (repeatable)")
    p.add_argument("--localhost-only", action="store_true",
                   help="apply xmetro's localhost-only DDS settings (as XMETRO_LOCALHOST_ONLY=1); default: the DDS "
                        "environment this command is started in")
    p.set_defaults(func=run)

    from ..bag.recover import __doc__ as recover_doc

    bag = subparsers.add_parser("bag", help="bag tools (recover a killed recording)",
                                description="Bag tools for MCAP bags in rosbag2's format.")
    tools = bag.add_subparsers(dest="bag_command", metavar="TOOL", required=True)
    r = tools.add_parser("recover", help="turn a killed recording into a complete, indexed bag",
                         description=recover_doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    r.add_argument("input", metavar="IN", help="the damaged bag: a .mcap file or a rosbag2 directory")
    r.add_argument("output", metavar="OUT", help="the new bag: OUT.mcap (from a file) or a directory (metadata.yaml "
                   "written)")
    r.add_argument("--compression", choices=["auto", "none", "zstd"], default="auto",
                   help="chunk compression of the output (auto: as the input's)")
    r.add_argument("--chunk-size", type=int, default=1024 * 1024, help="bytes per chunk (default 1 MiB)")
    r.set_defaults(func=run_recover)


def run_recover(args: argparse.Namespace) -> int:
    """``xmetro bag recover IN OUT``: 0 when recovered (losses are listed), 1 when nothing could be, 2 bad use."""
    from ..bag.reader import BagFormatError
    from ..bag.recover import recover
    from ..bag.writer import BagWriteError

    try:
        result = recover(args.input, args.output, compression=args.compression, chunk_size=args.chunk_size)
    except (BagFormatError, BagWriteError) as e:  # nothing readable, or the output could not be written
        print(f"xmetro bag recover: {e}", file=sys.stderr)
        return 1
    except (FileNotFoundError, FileExistsError, ValueError) as e:
        print(f"xmetro bag recover: {e}", file=sys.stderr)
        return 2
    print(result.describe())
    return 0


def run(args: argparse.Namespace) -> int:
    """``xmetro record``: record until SIGINT / SIGTERM / ``--duration``; returns the exit code."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    from ..bag.writer import BagWriteError, BagWriter
    from ..ros.dds_env import apply_requested_ros_env, dds_env_summary
    from ..ros.recorder import Recorder

    logging.basicConfig(level=logging.INFO, format="[xmetro record] %(levelname)s %(message)s", stream=sys.stderr)
    try:
        writer = BagWriter(
            args.output,
            compression=None if args.compression == "none" else args.compression,
            chunk_size=args.chunk_size,
            split_size=None if args.split_size is None else int(args.split_size * 1e6),
            split_duration=args.split_duration,
        )
    except (ValueError, OSError) as e:
        print(f"xmetro record: {e}", file=sys.stderr)
        return 2

    stop = threading.Event()
    reason = ["end"]

    def on_signal(signum: int, _frame: Any) -> None:
        reason[0] = signal.Signals(signum).name
        stop.set()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    apply_requested_ros_env(bool(getattr(args, "localhost_only", False)))
    logging.info("DDS environment: %s", dds_env_summary())
    ctx = Context()
    rclpy.init(context=ctx, signal_handler_options=SignalHandlerOptions.NO)
    rc = 0
    recorder = None
    try:
        node = rclpy.create_node("xmetro_recorder", context=ctx)
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        recorder = Recorder(node, writer, args.topics or None, discovery_period=args.discovery_period,
                            qos_depth=args.qos_depth, exclude=args.exclude)
        print(f"recording to {args.output} ({'all topics' if not args.topics else ', '.join(args.topics)})",
              flush=True)
        t0 = time.monotonic()
        next_progress = t0
        announced: set[str] = set()
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.05)
            for t in recorder.subscriptions:
                if t not in announced:
                    announced.add(t)
                    print(f"subscribed {t} {writer.topics[t].type_name}", flush=True)
            if recorder.error is not None:
                print(f"xmetro record: {recorder.error}", file=sys.stderr, flush=True)
                rc = 1
                break
            now = time.monotonic()
            if args.progress and now >= next_progress:
                next_progress = now + args.progress
                print("progress " + " ".join(f"{t}={n}" for t, n in sorted(recorder.counts.items())), flush=True)
            if args.duration is not None and now - t0 >= args.duration:
                reason[0] = "duration"
                break
        recorder.close()
        executor.shutdown(timeout_sec=2.0)
        node.destroy_node()
    finally:
        ctx.try_shutdown()
        try:
            writer.close()
        except BagWriteError as e:
            print(f"xmetro record: {e}", file=sys.stderr)
            rc = 1
        for s, h in old.items():
            signal.signal(s, h)
    print(f"stopped ({reason[0]}): {writer.message_count} messages in {len(writer.files)} file(s) at {args.output}")
    for t, topic in sorted(writer.topics.items()):
        print(f"  {t} [{topic.type_name}]: {topic.count}")
    if recorder is not None:
        for t, ty in sorted(recorder.unknown_types.items()):
            print(f"  skipped {t}: type {ty} not installed")
    return rc


def main(argv: list[str] | None = None) -> int:
    """``python -m xmetro_ros.apps.record record|bag ...``: the same commands without the other areas' CLIs."""
    parser = argparse.ArgumentParser(prog="xmetro")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
