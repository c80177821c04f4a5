"""A line-scanner driver's stream into a real ``xmetro_node`` process (``profile_input``): sustained points per
second and the latency from a profile's stamp to its judged output, at 300 Hz and 1 kHz of 2,048-point profiles
(0.6 and 2 M points/s). Writes bench/results/profiles.json.

Three processes: the driver + robot (a child process: sam-xl/scancontrol's PointCloud2 layout, reliable depth 10,
stamped with the wall clock at publish; /tf at 250 Hz and the hand-eye on /tf_static), ``xmetro_node`` (a child
process: config/xmetro.yaml, ``scan_trigger: count``: scans of 200 profiles, or a stream judged in chunks of 100 with
8 rows of context, ``stream_context_rows``), and this one, which listens to
``~/quality`` and /diagnostics. The sensor sweeps a gently curved surface 90 mm below it (every point a return) at
5 profiles/mm. A profile's latency = the wall-clock time its scan's ScanQuality arrives here − the profile's stamp
(assembly wait + tf wait + queue + judging + transport). What the node cannot judge in time is dropped by its queue
and accounted: profiles_received = judged + dropped + waiting (from /diagnostics, checked at the end).

    python bench/bench_profiles.py [--seconds 10] [--rates 300 1000]
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench" / "results" / "profiles.json"
WIDTH = 2048
DIRECTION_DENSITY = 5.0  # profiles per mm


def driver(rate_hz: float, seconds: float) -> int:
    """The driver + robot process: profiles at ``rate_hz`` for ``seconds`` after the node is matched."""
    import rclpy
    from builtin_interfaces.msg import Time
    from geometry_msgs.msg import TransformStamped
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from tf2_msgs.msg import TFMessage

    sys.path.insert(0, str(ROOT / "test"))
    from driver_emulators import DRIVERS

    ctx = rclpy.context.Context()
    rclpy.init(context=ctx)
    node = Node("bench_driver", context=ctx)
    drv = DRIVERS["scancontrol_samxl"]
    pub = node.create_publisher(type(drv.builder(np.zeros((2, 3)) + 0.09, 1).msg), "profiles", drv.qos)
    rel = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.VOLATILE)
    pub_tf = node.create_publisher(TFMessage, "/tf", rel)
    pub_static = node.create_publisher(TFMessage, "/tf_static", QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL))

    def tf(parent: str, child: str, stamp_ns: int, y: float) -> TransformStamped:
        t = TransformStamped()
        t.header.frame_id, t.child_frame_id = parent, child
        t.header.stamp = Time(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
        t.transform.translation.y = y
        t.transform.translation.z = 0.09
        t.transform.rotation.x = 1.0  # a half turn about x: the sensor looks down (sensor z = world −z)
        t.transform.rotation.w = 0.0
        return t

    deadline = time.monotonic() + 60
    while pub.get_subscription_count() == 0 or pub_tf.get_subscription_count() == 0:
        if time.monotonic() > deadline:
            print("no subscriber", flush=True)
            return 1
        time.sleep(0.05)
    ident = tf("flange", "sensor", 0, 0.0)
    ident.transform.translation.z = 0.0
    ident.transform.rotation.x, ident.transform.rotation.w = 0.0, 1.0
    pub_static.publish(TFMessage(transforms=[ident]))
    speed = rate_hz / DIRECTION_DENSITY / 1000.0  # m/s: DIRECTION_DENSITY profiles per mm
    x = np.linspace(-0.063, 0.063, WIDTH)  # the fan at 90 mm (70°)
    z = 0.09 + 0.002 * np.sin(x / 0.01)
    pts = np.stack([x, np.zeros(WIDTH), z], axis=1)
    base = drv.builder(pts, 0, frame_id="sensor").msg
    time.sleep(1.0)  # the node matched the static transform
    print("GO", flush=True)
    t0 = time.time_ns()
    period = 1.0 / rate_hz
    n, next_tf = 0, t0
    start = time.monotonic()
    while time.monotonic() - start < seconds:
        now = time.time_ns()
        while next_tf <= now + 4_000_000:  # tf samples up to 4 ms ahead of the profiles (a robot driver's rate)
            pub_tf.publish(TFMessage(transforms=[tf("world", "flange", next_tf, speed * (next_tf - t0) / 1e9)]))
            next_tf += 4_000_000
        base.header.stamp = Time(sec=now // 10**9, nanosec=now % 10**9)
        pub.publish(base)
        n += 1
        sleep = start + n * period - time.monotonic()
        if sleep > 0:
            time.sleep(sleep)
    print(json.dumps({"sent": n, "seconds": time.monotonic() - start}), flush=True)
    node.destroy_node()
    ctx.try_shutdown()
    return 0


def run_rate(rate: float, seconds: float, rows: int, context: int) -> dict:
    import rclpy  # noqa: F401
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    from xmetro_ros.msg import ScanQuality
    from xmetro_ros.ros.dds_env import ros_env
    from xmetro_ros.ros.rclpy_util import NodeProcess, NodeSpinner, wait_for

    period_ns = round(1e9 / rate)
    proc = NodeProcess(params_file=str(ROOT / "config" / "xmetro.yaml"), params={
        "profile_input": True, "fixed_frame": "world", "scan_trigger": "count", "trigger_count": rows,
        "stream_context_rows": context,
        "trigger_gap": 0.1, "default_direction_density": DIRECTION_DENSITY * 1000.0,
        "default_exposure_time": 0.0005, "max_points": 4_000_000})
    proc.start(timeout=120)
    lock = threading.Lock()
    lat: list[np.ndarray] = []
    verdicts: list[int] = []
    diag: dict[str, str] = {}
    try:
        sp = NodeSpinner(lambda ctx: Node("bench_profiles", context=ctx))
        rel = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)

        def on_q(msg: ScanQuality) -> None:
            t = time.time_ns()
            first = int(msg.header.stamp.sec) * 10**9 + int(msg.header.stamp.nanosec)
            with lock:
                verdicts.append(int(msg.verdict) if msg.error_code == 0 else 100 + int(msg.error_code))
                if msg.error_code == 0:
                    n_rows = int(msg.points_received) // WIDTH
                    lat.append((t - (first + np.arange(n_rows) * period_ns)) / 1e6)

        def on_diag(msg: DiagnosticArray) -> None:
            with lock:
                for st in msg.status:
                    if st.name.startswith("xmetro_node"):
                        diag.clear()
                        diag.update({kv.key: kv.value for kv in st.values})

        sub_q = sp.node.create_subscription(ScanQuality, "/xmetro_node/quality", on_q, rel)
        sp.node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, rel)
        assert wait_for(lambda: sub_q.get_publisher_count() > 0, 60)
        drv = subprocess.Popen([sys.executable, __file__, "--driver", str(rate), "--seconds", str(seconds)],
                               stdout=subprocess.PIPE, text=True, env=ros_env(), cwd=ROOT)
        assert drv.stdout is not None
        out = drv.stdout.read()
        drv.wait(timeout=120)
        sent = json.loads(out.strip().splitlines()[-1])
        # the last scans: judged or dropped, nothing waiting
        wait_for(lambda: diag.get("profiles_waiting") == "0" and diag.get("profiles_received") == str(sent["sent"]),
                 30)
        time.sleep(1.5)
        with lock:
            d = dict(diag)
            all_lat = np.concatenate(lat) if lat else np.zeros(0)
        rec, judged = int(d["profiles_received"]), int(d["profiles_judged"])
        dropped, waiting = int(d["profiles_dropped"]), int(d["profiles_waiting"])
        return {
            "rate_hz": rate, "points_per_profile": WIDTH, "offered_points_per_s": rate * WIDTH,
            "mode": f"stream: chunks of {rows} + {context} context rows" if context else f"scans of {rows} profiles",
            "seconds": round(sent["seconds"], 2), "profiles_sent": sent["sent"], "profiles_received": rec,
            "profiles_judged": judged, "profiles_dropped": dropped, "profiles_waiting": waiting,
            "dropped_by_reason": d.get("profiles_dropped_by_reason", ""),
            "profiles_lost": int(d.get("profiles_lost", 0)),
            "accounting_balanced": rec == judged + dropped + waiting,
            "lost_in_transport": sent["sent"] - rec,
            "judged_points_per_s": round(judged * WIDTH / sent["seconds"]),
            "scans_judged": len([v for v in verdicts if v < 100]), "verdicts": sorted(set(verdicts)),
            "latency_ms_p50": round(float(np.percentile(all_lat, 50)), 1) if all_lat.size else None,
            "latency_ms_p99": round(float(np.percentile(all_lat, 99)), 1) if all_lat.size else None,
            "latency_ms_max": round(float(all_lat.max()), 1) if all_lat.size else None,
        }
    finally:
        try:
            sp.close()
        except Exception:
            pass
        proc.stop()


def streaming_accuracy(chunks: list[int], context: int) -> dict:
    """Judging a pass in chunks vs whole (no DDS: the node's core and ProfileStream): the 55 mm sphere at 15/5/2
    streamed as keyence_ljv publishes it; flags agreement, |Δd| and the MAE against the simulator's systematic
    error, per chunk size."""
    sys.path.insert(0, str(ROOT / "test"))
    from driver_emulators import DRIVERS
    from stream_rig import sim_pass

    from xmetro_ros.ros.cloud import xyz_fields
    from xmetro_ros.ros.convert import settings_to_msg
    from xmetro_ros.ros.core import XmetroCore
    from xmetro_ros.ros.params import PARAMS
    from xmetro_ros.ros.profile_stream import stream_from_values
    from xmetro_ros.scan.artifacts import Sphere
    from xmetro_ros.scan.scanner import ScannerModel, ScanSettings
    from xmetro_ros.sim import simulate_scan

    settings = ScanSettings(15.0, 5.0, 2.0)
    scanner = ScannerModel.load()
    scan = simulate_scan(Sphere(27.5, np.zeros(3)), settings, seed=3)
    sp = sim_pass(scan, scanner)
    msgs = [DRIVERS["keyence_ljv"].builder(sp.profiles[i].astype(float), int(sp.stamps_ns[i]), frame_id="sensor").msg
            for i in range(len(sp.stamps_ns))]
    names = ["dx", "dy", "dz", "flags"]

    def judged(values: dict) -> np.ndarray:
        core = XmetroCore({p.name: p.default for p in PARAMS} | {"profile_input": True, "fixed_frame": "artifact"}
                          | values)
        core.add_settings(settings_to_msg(settings, scan.pose, "artifact", int(sp.stamps_ns[0]) - 1, scanner.id))
        st = stream_from_values(core.values)
        sp.feed(st.tf_buffer)
        a, _ = st.profiles(msgs, 0.0)
        b, _ = st.flush(10.0)
        out = []
        for asm in a + b:
            m, posed = core.posed_input(asm)
            dev = core.judge(m, posed=posed).deviations
            _xyz, f = xyz_fields(dev, names)
            out.append(np.stack([f[n] for n in names], axis=1).astype(float).reshape(dev.height, dev.width, 4))
        return np.concatenate(out)

    whole = judged({"scan_trigger": "count", "trigger_count": 100_000})
    truth = -np.asarray(scan.expected_error) / 1000.0
    runs = []
    for c in chunks:
        part = judged({"scan_trigger": "count", "trigger_count": c, "stream_context_rows": context})
        both = np.isfinite(whole[..., :3]).all(axis=2) & np.isfinite(part[..., :3]).all(axis=2)
        dd = np.abs(whole[..., :3] - part[..., :3])[both].max(axis=1) * 1e6
        same = float((whole[..., 3] == part[..., 3]).mean())
        runs.append({"chunk_rows": c, "context_rows": context, "flags_same": same,
                     "abs_dd_um_p50": float(np.median(dd)), "abs_dd_um_max": float(dd.max()),
                     "mae_truth_um_whole": float(np.abs(whole[..., :3] - truth)[both].mean() * 1e6),
                     "mae_truth_um_chunked": float(np.abs(part[..., :3] - truth)[both].mean() * 1e6)})
    return {"pass": f"55 mm sphere at 15/5/2, {len(msgs)} profiles", "runs": runs}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--rates", type=float, nargs="+", default=[300.0, 1000.0])
    ap.add_argument("--modes", nargs="+", default=["200:0", "100:8"],
                    help="ROWS:CONTEXT per run: scans of ROWS profiles (CONTEXT 0) or a stream in chunks of ROWS "
                         "with CONTEXT rows of context (stream_context_rows)")
    ap.add_argument("--driver", type=float, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--accuracy-only", action="store_true", help="only the chunked-vs-whole comparison (no DDS); "
                    "merged into the existing results file")
    a = ap.parse_args()
    if a.driver is not None:
        return driver(a.driver, a.seconds)
    accuracy = streaming_accuracy([60, 150], 6)
    if a.accuracy_only:
        doc = json.loads(OUT.read_text())
        doc["streaming_accuracy"] = accuracy
        OUT.write_text(json.dumps(doc, indent=1) + "\n")
        print(json.dumps(accuracy))
        return 0
    results = [run_rate(r, a.seconds, *(int(x) for x in m.split(":"))) for m in a.modes for r in a.rates]
    doc = {"machine": f"{platform.node()} ({platform.processor() or platform.machine()}), "
                      f"{__import__('os').cpu_count()} cores",
           "runs": results, "streaming_accuracy": accuracy}
    OUT.write_text(json.dumps(doc, indent=1) + "\n")
    for r in results:
        print(json.dumps(r))
    return 0


if __name__ == "__main__":
    sys.exit(main())
