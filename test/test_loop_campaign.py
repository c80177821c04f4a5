"""`xmetro loop --campaign`: the loop reads a calibration campaign (several certified spheres, known or fitted
positions) through campaign_file / campaign_data; a fitted position is never allowed to create an effect: the fit's
location error leaves n·δc on every point, which position-like candidates (x, y, z, scan position) would "explain"
across clouds — with fitted centres they are traced, reported as barred, and never selected."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_loop import sim_scan

from xmetro_ros.calibrate.campaign_file import CampaignError
from xmetro_ros.loop.candidates import POSITION_LIKE
from xmetro_ros.loop.inputs import from_campaign, from_scans
from xmetro_ros.loop.model import GivenModel, fit_family
from xmetro_ros.loop.run import LoopConfig, run_loop
from xmetro_ros.loop.trace import TraceConfig
from xmetro_ros.scan.scanner import ScannerModel

ROOT = Path(__file__).resolve().parents[1]
SEEDS = range(500, 510)
CFG = dict(iterations=120, max_iter=1, trace=TraceConfig(n_perm=49))


def _campaign(tmp: Path, scans: list, fitted: bool) -> Path:
    """One recording per scan; each scan shows one certified sphere (three sizes), known or fitted."""
    (tmp / "xm-ls90.yaml").write_text((ROOT / "config" / "scanners" / "default.yaml").read_text())
    arts, recs = {}, []
    for i, s in enumerate(scans):
        aid = f"ball_r{s.artifact.radius:g}"
        arts[aid] = {"id": aid, "kind": "sphere", "radius_mm": s.artifact.radius, "certificate": f"C-{aid}"}
        (tmp / f"run{i}.mcap").write_bytes(b"")
        c = [float(v) for v in s.artifact.center]
        pos = {"fit": [c[0] + 0.4, c[1] - 0.3, c[2] + 0.2]} if fitted else {"known": c, "uncertainty_mm": 0.001,
                                                                              "source": "CMM"}
        recs.append({"bag": f"run{i}.mcap", "placements": [{"artifact": aid, "position": pos}]})
    d = {"format": "xmetro-campaign/1", "scanner": {"id": "xm-ls90", "description": "xm-ls90.yaml"},
         "artifacts": list(arts.values()), "recordings": recs}
    p = tmp / "campaign.yaml"
    p.write_text(yaml.safe_dump(d, sort_keys=False))
    return p


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    clean = from_scans([sim_scan(1000 + k) for k in range(6)])
    model = GivenModel(fit_family("catboost", clean.X, clean.errors, clean.feature_names, seed=0, iterations=150))
    scans = [sim_scan(s) for s in SEEDS]
    by_bag = {f"run{i}.mcap": [s] for i, s in enumerate(scans)}
    tmp = tmp_path_factory.mktemp("camp")
    paths = {}
    for fitted in (False, True):
        d = tmp / ("fitted" if fitted else "known")
        d.mkdir()
        paths[fitted] = _campaign(d, scans, fitted)
    return model, scans, (lambda rec, scanner: by_bag[rec.bag.name]), paths


def test_campaign_input_known_and_fitted(setup):
    _model, scans, read, paths = setup
    known = from_campaign(paths[False], read)
    fitted = from_campaign(paths[True], read)
    assert len(known.groups) == len(fitted.groups) == len(scans) and known.source == "campaign"
    assert known.artifact["fitted_groups"] == [] and fitted.artifact["fitted_groups"] == list(range(len(scans)))
    assert {a["artifact_id"] for a in known.artifact["per_group"]} == {f"ball_r{r:g}" for r in (17.5, 22.5, 27.5)}
    # known positions: exactly the table of the scans with their own (true) spheres
    direct = from_scans(scans)
    assert known.n == direct.n and np.allclose(known.errors, direct.errors, atol=1e-9)
    # fitted centres absorb what looks like a shift of the sphere: the targets differ by n·δc (µm)
    diff = np.abs(np.einsum("ij,ij->i", fitted.errors - known.errors, fitted.normals))
    assert 1e-4 < np.median(diff) < 0.05


def test_fitted_positions_never_create_an_effect(setup):
    """The same scans, same model, same seed: with known centres nothing is found; with fitted centres the fit's
    location errors make position-like candidates significant — they are reported as barred, never selected."""
    model, _scans, read, paths = setup
    res_k = run_loop(from_campaign(paths[False], read), LoopConfig(seed=0, **CFG), given=model).report
    res_f = run_loop(from_campaign(paths[True], read), LoopConfig(seed=0, **CFG), given=model).report
    assert res_k["selected"] is None and res_k["diagnostic"]["barred_by_fitted_positions"] == []
    cand = {c["name"]: c for c in res_f["candidates"]}
    barred = [c for c in cand.values() if c["confounded"]]
    assert {c["name"] for c in barred} == POSITION_LIKE & set(cand)
    sig = [c["name"] for c in barred if c["significant"]]
    assert sig, [(c["name"], c["score"], c["significant_by"]) for c in barred]  # the guard has work to do
    assert {b["variable"] for b in res_f["diagnostic"]["barred_by_fitted_positions"]} == set(sig)
    sel = res_f["selected"]
    assert sel is None or sel["name"] not in POSITION_LIKE
    assert not set(res_f["predictive"]["added"]) & POSITION_LIKE


def test_cli_campaign(setup, tmp_path, monkeypatch, capsys):
    from test_loop import _cli

    from xmetro_ros.apps import loop as app

    _model, _scans, read, paths = setup
    monkeypatch.setattr(app, "_read_recording", read)
    out = tmp_path / "out"
    assert _cli(["--campaign", str(paths[True]), "--out", str(out), "--n-perm", "29", "--iterations", "60",
                 "--max-iter", "1"]) == 0, capsys.readouterr().err
    rep = json.loads((out / "report.json").read_text())
    assert rep["source"] == "campaign" and rep["n_groups"] == len(SEEDS)
    assert not set(rep["predictive"]["added"]) & POSITION_LIKE
    assert _cli(["--campaign", str(paths[True]), "in.mcap", "--out", str(out)]) == 2
    assert "give no inputs" in capsys.readouterr().err
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"format": "xmetro-campaign/1"}))
    assert _cli(["--campaign", str(bad), "--out", str(out)]) == 2
    with pytest.raises(CampaignError):
        from_campaign(bad, read)
    assert ScannerModel.load().id == "xm-ls90"
