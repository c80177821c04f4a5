"""Bag throughput: BagWriter (record path) and BagReader next to rosbags and the mcap library on the same files.

Writes bench/results/bag.json. Payload: PointCloud2 messages of 200,000 points × (x, y, z, intensity) float32
(3.2 MB each), pre-serialized for the storage-only numbers. MB = 1e6 bytes of message payload. Each figure is the
best of ``REPEATS`` runs (this machine is shared and noisy); ratios compare numbers taken in the same run.
"""

from __future__ import annotations

import json
import platform
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
from rclpy.serialization import serialize_message
from std_msgs.msg import Header

from xmetro_ros.bag import qos_profiles
from xmetro_ros.bag.reader import BagReader
from xmetro_ros.bag.writer import BagWriter
from xmetro_ros.ros.cloud import create_cloud_from_arrays

HERE = Path(__file__).resolve().parent
N_MSGS = 24
N_POINTS = 200_000
REPEATS = 5


def _clouds() -> list:
    rng = np.random.default_rng(0)
    out = []
    for _i in range(N_MSGS):
        arrays = {k: rng.normal(size=N_POINTS).astype(np.float32) for k in ("x", "y", "z", "intensity")}
        out.append(create_cloud_from_arrays(Header(frame_id="artifact"), arrays, height=1, width=N_POINTS))
    return out


def _best(fn) -> float:
    times = []
    for _ in range(REPEATS):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> int:
    clouds = _clouds()
    raws = [serialize_message(c) for c in clouds]
    mb = sum(len(r) for r in raws) / 1e6
    tmp = Path(tempfile.mkdtemp(prefix="bench_bag_"))
    res: dict = {"payload_mb": round(mb, 1), "messages": N_MSGS, "points_per_message": N_POINTS,
                 "repeats": REPEATS, "host": platform.node(), "write_mb_s": {}, "read_mb_s": {}}
    try:
        counter = [0]

        def write(compression, objects=False):
            def run():
                counter[0] += 1
                p = tmp / f"w{counter[0]}"
                with BagWriter(p, compression=compression) as w:
                    w.add_topic("/scan", "sensor_msgs/msg/PointCloud2", [qos_profiles.CLOUD])
                    for i, m in enumerate(clouds if objects else raws):
                        w.write("/scan", m, (i + 1) * 1_000_000)
                return p
            return run

        for name, fn in [("xmetro_uncompressed", write(None)), ("xmetro_zstd", write("zstd")),
                         ("xmetro_uncompressed_with_serialization", write(None, objects=True))]:
            res["write_mb_s"][name] = round(mb / _best(fn), 1)
        plain = write(None)()
        zst = write("zstd")()

        def ours(path, deserialize):
            def run():
                n = sum(1 for _ in BagReader(path).messages(deserialize=deserialize))
                assert n == N_MSGS
            return run

        def rosbags_raw(path, deserialize):
            from rosbags.highlevel import AnyReader
            from rosbags.typesys import Stores, get_typestore

            store = get_typestore(Stores.ROS2_KILTED)

            def run():
                with AnyReader([path], default_typestore=store) as ar:
                    n = 0
                    for c, _t, raw in ar.messages():
                        if deserialize:
                            ar.deserialize(raw, c.msgtype)
                        n += 1
                assert n == N_MSGS
            return run

        def mcap_lib(path):
            from mcap.reader import make_reader

            def run():
                n = 0
                for f in sorted(path.glob("*.mcap")):
                    with open(f, "rb") as fh:
                        n += sum(1 for _ in make_reader(fh).iter_messages())
                assert n == N_MSGS
            return run

        for tag, path in [("uncompressed", plain), ("zstd", zst)]:
            res["read_mb_s"][f"xmetro_raw_{tag}"] = round(mb / _best(ours(path, False)), 1)
            res["read_mb_s"][f"xmetro_deserialize_{tag}"] = round(mb / _best(ours(path, True)), 1)
            res["read_mb_s"][f"rosbags_raw_{tag}"] = round(mb / _best(rosbags_raw(path, False)), 1)
            res["read_mb_s"][f"rosbags_deserialize_{tag}"] = round(mb / _best(rosbags_raw(path, True)), 1)
            res["read_mb_s"][f"mcap_library_{tag}"] = round(mb / _best(mcap_lib(path)), 1)
        r = res["read_mb_s"]
        res["ratios"] = {
            "xmetro_raw_over_rosbags_raw_uncompressed": round(r["xmetro_raw_uncompressed"]
                                                              / r["rosbags_raw_uncompressed"], 2),
            "xmetro_raw_over_rosbags_raw_zstd": round(r["xmetro_raw_zstd"] / r["rosbags_raw_zstd"], 2),
            "xmetro_deserialize_over_rosbags_deserialize_uncompressed": round(
                r["xmetro_deserialize_uncompressed"] / r["rosbags_deserialize_uncompressed"], 2),
        }
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    out = HERE / "results" / "bag.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(res, indent=2) + "\n")
    print(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
