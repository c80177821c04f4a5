"""`xmetro calibrate` end to end on recordings made as a driver makes them (PointCloud2 + ScannerSettings, no
simulator metadata) of a foreign scanner described only in data-sheet terms, with spheres off the origin."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from xmetro_ros.bag.writer import BagWriter
from xmetro_ros.judge.inference import ModelSet
from xmetro_ros.ros.convert import scan_to_cloud, settings_to_msg
from xmetro_ros.scan.artifacts import Sphere
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings
from xmetro_ros.sim import simulate_scan

RANGES = {"lateral_density": [0.5, 100], "direction_density": [0.1, 50], "exposure_ms": [0.005, 50]}
SHEET = {"id": "ls-200", "serial": "SN-7", "measuring_range_mm": [150.0, 250.0], "field_of_view_mm": [100.0, 180.0],
         "triangulation_angle_deg": 20.0, "camera_side": "-y", "settings_range": RANGES,
         "default_settings": {"lateral_density": 4.0, "direction_density": 2.0, "exposure_ms": 0.5}}
CENTRES = {"ball_a": (30.0, -8.0, 0.0), "ball_b": (-32.0, 6.0, 2.0)}
RADIUS = 12.7


def _record(path: Path, scanner: ScannerModel, n: int, seed: int) -> list:
    """A bag as a driver records it: per scan one ScannerSettings and one PointCloud2 showing both balls."""
    truths = []
    levels = [(4.0, 2.0, 0.5), (6.0, 3.0, 2.0), (4.0, 3.0, 0.2), (6.0, 2.0, 0.5)]
    with BagWriter(path) as w:
        w.add_topic("/scanner_settings", "xmetro_ros/msg/ScannerSettings")
        w.add_topic("/scan", "sensor_msgs/msg/PointCloud2")
        for k in range(n):
            s = ScanSettings(*levels[k % len(levels)])
            a = simulate_scan(Sphere(RADIUS, CENTRES["ball_a"]), s, scanner=scanner, seed=seed + 2 * k)
            b = simulate_scan(Sphere(RADIUS, CENTRES["ball_b"]), s, scanner=scanner, seed=seed + 2 * k + 1)
            stamp = (k + 1) * 10**9
            scan = replace(a, points=np.concatenate([a.points.reshape(-1, 3), b.points.reshape(-1, 3)]), fields={},
                           artifact=None, expected_error=None, noise_std=None, injected_outlier=None, stamp_ns=stamp)
            w.write("/scanner_settings", settings_to_msg(s, a.pose, scan.frame_id, stamp - 1000, scanner.id),
                    stamp - 1000)
            w.write("/scan", scan_to_cloud(scan, stamp), stamp)
            truths.append((a, b))
    return truths


@pytest.mark.timeout(900)
def test_calibrate_a_foreign_scanner_from_driver_recordings(tmp_path):
    from xmetro_ros.apps.cli import main

    sheet = {**SHEET, "effects": ScannerModel.load().effects}
    (tmp_path / "ls-200.yaml").write_text(yaml.safe_dump(sheet))
    scanner = ScannerModel.from_dict(sheet, "ls-200.yaml")
    _record(tmp_path / "run1.mcap", scanner, 12, seed=10)
    camp = {"format": "xmetro-campaign/1",
            "scanner": {"id": "ls-200", "serial": "SN-7", "description": "ls-200.yaml"},
            "artifacts": [{"id": "ball_a", "diameter_mm": 2 * RADIUS, "size_uncertainty_mm": 0.0008,
                           "certificate": "C-1"},
                          {"id": "ball_b", "diameter_mm": 2 * RADIUS, "certificate": "C-2"}],
            "recordings": [{"bag": "run1.mcap", "placements": [
                {"artifact": "ball_a", "position": {"known": list(CENTRES["ball_a"]), "uncertainty_mm": 0.002,
                                                    "source": "CMM"}},
                {"artifact": "ball_b", "position": {"known": list(CENTRES["ball_b"]), "uncertainty_mm": 0.002,
                                                    "source": "CMM"}}]}]}
    (tmp_path / "campaign.yaml").write_text(yaml.safe_dump(camp, sort_keys=False))
    out = tmp_path / "cal"
    assert main(["calibrate", str(tmp_path / "campaign.yaml"), "--out", str(out), "--profile", "micro",
                 "--families", "catboost"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["checks"]["n_measurements"] == 24 and report["checks"]["levels_from_campaign"]
    assert report["positions"] == "known"
    assert set(report["vdi2634"]["per_settings"]) == {ScanSettings(*v).label() for v in
                                                      [(4.0, 2.0, 0.5), (6.0, 3.0, 2.0), (4.0, 3.0, 0.2),
                                                       (6.0, 2.0, 0.5)]}
    assert "VDI/VDE 2634-2" in (out / "report.md").read_text()
    ms = ModelSet.load(out / "models" / "catboost")
    card = ms.card
    assert card["scanner"]["id"] == "ls-200" and card["scanner"]["serial"] == "SN-7"
    assert card["campaign"]["sha256"] and card["campaign"]["artifacts"][0]["certificate"] == "C-1"
    assert card["trained_by"].startswith("xmetro calibrate campaign.yaml")
    # uncertainty: 3 + 3 of the 12 scans held out BY SCAN (both balls of a scan together) for the conformal
    # calibration and the coverage check; the card carries the calibration and the domain of the training rows
    held = report["uncertainty"]["held_out"]
    assert len(held["calibration"]) == 6 and len(held["coverage"]) == 6
    scans_of = {part: {lab.rsplit(" ", 1)[0] for lab in held[part]} for part in held}
    assert len(scans_of["calibration"]) == 3 and not scans_of["calibration"] & scans_of["coverage"]
    assert ms.calibrated and card["domain_mv"]["n_train"] > 0
    assert card["uncertainty"]["calibration_clouds"] == held["calibration"]
    cov = report["uncertainty"]["families"]["catboost"]["coverage"]
    for ax in "xyz":  # constant σ̂ (catboost): coverage on 3 new scans near the nominal 95 %
        assert 0.85 <= cov[ax]["coverage"] <= 1.0, (ax, cov[ax])
    assert "Interval coverage (95 %) on held-out scans" in (out / "report.md").read_text()
    # report.html: self-contained, the same VDI/VDE 2634-2 figures per settings, deviation maps of held-out scans
    # embedded (and written as PNG files)
    page = (out / "report.html").read_text()
    assert "VDI/VDE 2634-2" in page and "Interval coverage (95 %) on held-out scans" in page
    for label, d in report["vdi2634"]["per_settings"].items():
        pf, ps = (f"{d[k]['max_abs'] * 1e3:.1f}" for k in ("PF_mm", "PS_mm"))
        assert label in page and f"<td>{pf}</td><td>{ps}</td>" in page
    maps = report["deviation_maps"]
    assert len(maps) == 2 and all(m["part"] == "coverage" and m["family"] == "catboost" for m in maps)
    assert {m["scan"] for m in maps} <= set(held["coverage"])
    assert page.count("src='data:image/png;base64,iVBOR") == len(maps)  # PNG signature, base64
    for m in maps:
        assert (out / m["file"]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and m["n_points"] > 500
        assert 0 < m["mae_normal_um"] < 50 and all(0.5 < m["within_U"][ax] <= 1.0 for ax in "xyz")
        assert m["file"] in (out / "report.md").read_text()
    # the model learned something real about this scanner (micro profile, 12 training measurements): held-out R² clearly
    # above zero on every axis, for held-out points and held-out configurations (measured 0.12-0.37)
    for split in ("point", "cloud"):
        for ax in "xyz":
            assert report["models"][split]["catboost"][ax]["r2"]["mean"] > 0.08, (split, ax)


def test_a_campaign_error_is_a_clear_exit(tmp_path, capsys):
    from xmetro_ros.apps.cli import main

    (tmp_path / "c.yaml").write_text("format: xmetro-campaign/1\nscanner: {id: x}\n")
    assert main(["calibrate", str(tmp_path / "c.yaml"), "--out", str(tmp_path / "o")]) == 2
    assert "scanner needs an id and a description" in capsys.readouterr().err


def test_calibrate_from_the_virtual_prior(tmp_path, capsys):
    """``--prior``: the pointnet_multi network starts from a model set's network (here the packaged default) and is
    fine-tuned on the campaign; the card records the prior; a prior of another layout is refused before any
    recording is read."""
    from xmetro_ros.apps.cli import main
    from xmetro_ros.learn.prior import load_prior

    sheet = {**SHEET, "effects": ScannerModel.load().effects}
    (tmp_path / "ls-200.yaml").write_text(yaml.safe_dump(sheet))
    _record(tmp_path / "run1.mcap", ScannerModel.from_dict(sheet, "ls-200.yaml"), 4, seed=30)
    camp = {"format": "xmetro-campaign/1", "scanner": {"id": "ls-200", "description": "ls-200.yaml"},
            "artifacts": [{"id": "ball_a", "diameter_mm": 2 * RADIUS}],
            "recordings": [{"bag": "run1.mcap", "placements": [
                {"artifact": "ball_a", "position": {"known": list(CENTRES["ball_a"]), "source": "CMM"}}]}]}
    (tmp_path / "campaign.yaml").write_text(yaml.safe_dump(camp, sort_keys=False))
    args = ["calibrate", str(tmp_path / "campaign.yaml"), "--families", "pointnet_multi", "--prior", "default",
            "--max-points", "400"]
    # the packaged model's compact layout (32 / 64 / 32) is not the micro profile's (16 / 32 / 16)
    assert main([*args, "--out", str(tmp_path / "bad"), "--profile", "micro"]) == 2
    msg = capsys.readouterr().err
    assert "network layout differs from the pointnet_multi layout of --profile micro" in msg
    assert "block1 [32] (profile [16])" in msg and not (tmp_path / "bad").exists()
    assert main([*args[:-4], "--families", "catboost", "--prior", "default", "--out", str(tmp_path / "b2")]) == 2
    assert "--families catboost has none" in capsys.readouterr().err
    out = tmp_path / "cal"
    assert main([*args, "--out", str(out), "--profile", "quick"]) == 0
    card = ModelSet.load(out / "models" / "pointnet_multi").card
    prior = load_prior("default")
    assert card["prior"]["model_id"] == prior.card["id"] and card["prior"]["scanner"] == "xm-ls90"
    assert card["trained_by"].endswith("--prior default") and card["models"][0]["params"]["warm_start"]
    # fine-tuned FROM the prior: the network keeps the prior's input / target normalisation (a fresh fit takes the
    # campaign's statistics), its weights moved
    tuned = load_prior(out / "models" / "pointnet_multi").module
    for buf in ("x_mean", "x_std", "y_scale"):
        assert np.array_equal(getattr(tuned, buf).numpy(), getattr(prior.module, buf).numpy()), buf
    assert not np.array_equal(tuned.block1[0].weight.detach().numpy(), prior.module.block1[0].weight.detach().numpy())
    report = json.loads((out / "report.json").read_text())
    assert report["prior"]["model_id"] == prior.card["id"] and "warm-started from the prior" in (
        out / "report.html").read_text()
