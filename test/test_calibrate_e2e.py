"""Acceptance of issue 16 through the real path: a foreign scanner (data-sheet geometry, effect magnitudes unlike the
default) simulated and PUBLISHED OVER DDS into a real ``xmetro record`` process, a hand-written campaign file,
``xmetro calibrate``, then a node started with the result judges NEW recordings of that scanner (replayed into it
with ``xmetro replay``'s ``replay_bag``). Judged against the simulator truth kept in the test:

- accuracy: MAE of the published deviations against the actual deviation (measured − nominal, the published sign)
  at the same points, against the oracle floor = MAE of the simulator's own noise-free expected error as a
  predictor of that error;
- intervals: coverage of the published U (95 %) on the new clouds (known positions).
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_calibrate import CENTRES, RADIUS, SHEET

from xmetro_ros.bag.writer import BagWriter
from xmetro_ros.scan.artifacts import Sphere
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings
from xmetro_ros.scan.targets import published_deviation
from xmetro_ros.sim import simulate_scan

TIMEOUT = 60.0
LEVELS = [(4.0, 2.0, 0.5), (6.0, 3.0, 2.0), (4.0, 3.0, 0.2), (6.0, 2.0, 0.5)]
N_CAMPAIGN = 32  # scans (2 balls each) published into `xmetro record`
N_NEW = 8  # new scans (one ball each) judged by the node


def foreign_effects() -> dict:
    """The default effects with a few magnitudes changed: the foreign scanner is not the virtual one re-labelled."""
    eff = json.loads(json.dumps(ScannerModel.load().effects))
    eff["centroid"]["coefficient_mm"] *= 2.0
    eff["standoff"]["linear_mm"] *= 2.0
    eff["edge"]["max_mm"] *= 0.5
    eff["speckle"]["sigma_mm"] *= 0.8
    return eff


def _driver_scan(k: int, scanner: ScannerModel, seed: int, balls: tuple[str, ...]):
    """(driver scan without simulator metadata, stamp, settings, the per-ball simulated Scans)."""
    s = ScanSettings(*LEVELS[k % len(LEVELS)])
    sims = [simulate_scan(Sphere(RADIUS, CENTRES[b]), s, scanner=scanner, seed=seed + 7 * k + i)
            for i, b in enumerate(balls)]
    stamp = (k + 1) * 10**9
    pts = np.concatenate([a.points.reshape(-1, 3) for a in sims]) if len(sims) > 1 else sims[0].points
    scan = replace(sims[0], points=pts, fields={}, artifact=None, expected_error=None, noise_std=None,
                   injected_outlier=None, stamp_ns=stamp)
    return scan, stamp, s, sims


class _Record:
    """A real ``xmetro record`` process with its stdout collected (as test_bag_recorder's)."""

    def __init__(self, out: Path) -> None:
        from xmetro_ros.ros.dds_env import ros_env

        cmd = [sys.executable, "-m", "xmetro_ros.apps.record", "record", "-o", str(out), "--discovery-period",
               "0.2", "--progress", "0.1"]
        self.p = subprocess.Popen(cmd, env=ros_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.lines: list[str] = []
        self._t = threading.Thread(target=self._read, daemon=True)
        self._t.start()

    def _read(self) -> None:
        for line in self.p.stdout:
            self.lines.append(line.rstrip("\n"))

    def saw(self, text: str) -> bool:
        return any(text in line for line in list(self.lines))

    def count(self, topic: str) -> int:
        last = [line for line in list(self.lines) if line.startswith("progress")]
        if not last:
            return 0
        return {k: int(v) for k, v in (kv.split("=") for kv in last[-1].split()[1:])}.get(topic, 0)

    def stop(self) -> str:
        self.p.send_signal(signal.SIGINT)
        self.p.wait(timeout=TIMEOUT)
        self._t.join(timeout=5)
        return "\n".join(self.lines)

    def kill(self) -> None:
        if self.p.poll() is None:
            self.p.kill()
            self.p.wait(timeout=10)


def _publish_campaign(out: Path, scanner: ScannerModel) -> None:
    """A driver publishing ScannerSettings (transient-local) and PointCloud2 over DDS into `xmetro record`."""
    import rclpy
    from rclpy.duration import Duration
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    from xmetro_ros.msg import ScannerSettings
    from xmetro_ros.ros.convert import scan_to_cloud, settings_to_msg
    from xmetro_ros.ros.node import settings_qos
    from xmetro_ros.ros.rclpy_util import NodeSpinner, wait_for

    rec = _Record(out)
    try:
        with NodeSpinner(lambda ctx: rclpy.create_node("ls200_driver", context=ctx)) as sp:
            pub_set = sp.node.create_publisher(ScannerSettings, "/scanner_settings", settings_qos())
            pub_scan = sp.node.create_publisher(PointCloud2, "/scan",
                                                QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE))
            assert wait_for(lambda: rec.saw("subscribed /scan ") and rec.saw("subscribed /scanner_settings "),
                            TIMEOUT), rec.lines
            assert wait_for(lambda: pub_scan.get_subscription_count() > 0
                            and pub_set.get_subscription_count() > 0, TIMEOUT)
            for k in range(N_CAMPAIGN):
                scan, stamp, s, sims = _driver_scan(k, scanner, 100, ("ball_a", "ball_b"))
                pub_set.publish(settings_to_msg(s, sims[0].pose, scan.frame_id, stamp - 1000, scanner.id))
                pub_set.wait_for_all_acked(Duration(seconds=10))  # settings before their scan, as a driver does
                pub_scan.publish(scan_to_cloud(scan, stamp))
                pub_scan.wait_for_all_acked(Duration(seconds=10))
            assert wait_for(lambda: rec.count("/scan") >= N_CAMPAIGN, TIMEOUT), rec.lines[-5:]
        text = rec.stop()
    finally:
        rec.kill()
    assert rec.p.returncode == 0, text


def _new_recordings(path: Path, scanner: ScannerModel) -> list:
    """New recordings of the scanner (one ball per scan, organized grid), as a driver writes them; their Scans."""
    from xmetro_ros.ros.convert import scan_to_cloud, settings_to_msg

    truths = []
    with BagWriter(path) as w:
        w.add_topic("/scanner_settings", "xmetro_ros/msg/ScannerSettings")
        w.add_topic("/scan", "sensor_msgs/msg/PointCloud2")
        for k in range(N_NEW):
            ball = ("ball_a", "ball_b")[k % 2]
            scan, stamp, s, sims = _driver_scan(k, scanner, 5000, (ball,))
            w.write("/scanner_settings", settings_to_msg(s, sims[0].pose, scan.frame_id, stamp - 1000, scanner.id),
                    stamp - 1000)
            w.write("/scan", scan_to_cloud(scan, stamp), stamp)
            truths.append((ball, sims[0]))
    return truths


def _judge(outputs: Path, truths: list) -> dict:
    """Published deviations and U of the node vs the truth, matched point by point on the received coordinates."""
    from scipy.spatial import cKDTree

    from xmetro_ros.bag.reader import BagReader
    from xmetro_ros.ros.cloud import read_points

    devs = [m.msg for m in BagReader(outputs).read_all() if m.topic.endswith("/deviations")]
    assert len(devs) == len(truths), f"{len(devs)} deviations clouds for {len(truths)} scans"
    pred, unc, act, orc = [], [], [], []
    for msg, (ball, sim) in zip(devs, truths, strict=True):
        d = read_points(msg, skip_nans=False)
        pts = sim.points.reshape(-1, 3)
        ok = np.all(np.isfinite(pts), axis=1) & ~sim.injected_outlier.reshape(-1)
        idx = np.flatnonzero(ok)
        tree = cKDTree((pts[idx] * 1e-3).astype(np.float32).astype(np.float64))
        q = np.stack([d["x"], d["y"], d["z"]], 1).astype(np.float64)
        fin = np.all(np.isfinite(q), axis=1)
        dist, j = np.full(len(q), np.inf), np.zeros(len(q), int)
        dist[fin], j[fin] = tree.query(q[fin])
        hit = (dist < 1e-7) & np.all(np.isfinite(np.stack([d["dx"], d["dy"], d["dz"], d["ux"], d["uy"], d["uz"]],
                                                          1)), axis=1)
        rows = idx[j[hit]]
        y = published_deviation(Sphere(RADIUS, CENTRES[ball]).errors(pts[rows]))  # measured − nominal
        pred.append(np.stack([d["dx"], d["dy"], d["dz"]], 1)[hit] * 1e3)
        unc.append(np.stack([d["ux"], d["uy"], d["uz"]], 1)[hit] * 1e3)
        act.append(y)
        orc.append(published_deviation(sim.expected_error.reshape(-1, 3)[rows]))
    pred, unc, act, orc = (np.concatenate(v).astype(np.float64) for v in (pred, unc, act, orc))
    mae = np.abs(pred - act).mean(0)
    floor = np.abs(orc - act).mean(0)
    cov = (np.abs(act - pred) <= unc).mean(0)
    return {"n_points": len(act), "mae_um": (mae * 1e3).round(2).tolist(), "floor_um": (floor * 1e3).round(2).tolist(),
            "ratio": float(mae.mean() / floor.mean()), "ratio_axes": (mae / floor).round(3).tolist(),
            "coverage": cov.round(4).tolist()}


@pytest.mark.timeout(900)
@pytest.mark.parametrize("positions", ["known", "fitted"])
def test_foreign_scanner_recorded_over_dds_calibrated_and_judged_by_a_node(tmp_path, positions):
    from xmetro_ros.apps.calibrate import calibrate
    from xmetro_ros.apps.replay import replay_bag
    from xmetro_ros.ros.rclpy_util import NodeProcess

    sheet = {**SHEET, "effects": foreign_effects()}
    (tmp_path / "ls-200.yaml").write_text(yaml.safe_dump(sheet))
    scanner = ScannerModel.from_dict(sheet, "ls-200.yaml")
    _publish_campaign(tmp_path / "campaign_rec", scanner)
    if positions == "known":
        pos = {b: {"known": list(CENTRES[b]), "uncertainty_mm": 0.002, "source": "CMM"} for b in CENTRES}
    else:  # fitted with the certified size from a guess 1 mm off (the integrator knows roughly where the balls are)
        pos = {b: {"fit": [c + 1.0 for c in CENTRES[b]]} for b in CENTRES}
    camp = {"format": "xmetro-campaign/1",
            "scanner": {"id": "ls-200", "serial": "SN-7", "description": "ls-200.yaml"},
            "artifacts": [{"id": b, "diameter_mm": 2 * RADIUS, "size_uncertainty_mm": 0.0008, "certificate": f"C-{b}"}
                          for b in CENTRES],
            "recordings": [{"bag": "campaign_rec", "placements": [
                {"artifact": b, "position": pos[b]} for b in CENTRES]}]}
    (tmp_path / "campaign.yaml").write_text(yaml.safe_dump(camp, sort_keys=False))
    report = calibrate(tmp_path / "campaign.yaml", tmp_path / "cal", profile="quick", families=("pointnet_multi",))
    assert report["checks"]["n_measurements"] == 2 * N_CAMPAIGN
    unc = report["uncertainty"]["families"]["pointnet_multi"]
    print("calibrate: held-out coverage", {ax: unc["coverage"][ax].get("coverage") for ax in "xyz"},
          "multipliers", unc["multiplier"])

    truths = _new_recordings(tmp_path / "new.mcap", scanner)
    params = {"model_dir": str(tmp_path / "cal" / "models" / "pointnet_multi"),
              "scanner_config": str(tmp_path / "ls-200.yaml")}
    with NodeProcess(params=params) as node:
        res = replay_bag(tmp_path / "new.mcap", fast=True, record=tmp_path / "outputs.mcap")
        assert len(res.scans) == N_NEW, (res.losses, node.lines[-20:])
    got = _judge(tmp_path / "outputs.mcap", truths)
    print(f"node on new recordings ({positions} positions):", got)
    assert got["n_points"] > 20_000
    if positions == "known":
        # the acceptance (docs/calibration.md, "Acceptance"; measured: ratio 1.12, per axis 1.07-1.17, coverage
        # 95.2 / 94.5 / 95.7 %)
        assert got["ratio"] <= 1.25 and max(got["ratio_axes"]) <= 1.25, got
        for c in got["coverage"]:
            assert 0.94 <= c <= 0.96, got
    else:
        # the documented loss of fitted positions: location errors are not learned, the node cannot predict them
        # and the intervals (calibrated on fitted-centre targets) miss them
        assert got["ratio"] > 1.25, got
