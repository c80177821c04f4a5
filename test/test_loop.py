"""Closed loop (xmetro_ros.loop): undeclared effects injected into small simulated sphere scans are traced to the
right variable and corrected; no effect → none found; bad input → clear errors. Fixed seeds, small clouds."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import need_shared

from xmetro_ros.loop.candidates import build_candidates
from xmetro_ros.loop.data import LoopInputError
from xmetro_ros.loop.inputs import from_scans, load_inputs
from xmetro_ros.loop.model import GivenModel, fit_family
from xmetro_ros.loop.run import LoopConfig, run_loop
from xmetro_ros.loop.trace import TraceConfig, holm
from xmetro_ros.ros.scan_io import read_scans
from xmetro_ros.scan.artifacts import ArtifactSpecError, Sphere
from xmetro_ros.scan.geometry import HeadPose, unit
from xmetro_ros.scan.scan import Scan
from xmetro_ros.scan.scanner import ScanSettings

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
VIB_PERIOD_S = 0.2 / 6  # a scan of 40 profiles at 200 profiles/s lasts 0.2 s: 6 periods per scan


def sim_scan(seed: int, effect: str | None = None, mag: float = 0.0, H: int = 40, W: int = 60,
             noise: float = 0.004, n_pass: int = 4, also: dict[str, float] | None = None) -> Scan:
    """A sphere (random radius / placement) scanned by a head looking down; points displaced along the laser ray by
    a declared geometric error (a function of incidence and height) + noise + the undeclared ``effect`` (mm).
    Half the scans run with the head turned 180° about Z (scanning −Y, laser line along −X) and every scan starts a
    random distance before the sphere, so that scan time and line position are not functions of the geometry."""
    rng = np.random.default_rng(seed)
    radius = float(rng.choice([17.5, 22.5, 27.5]))
    art = Sphere(radius, tuple(rng.uniform(-3, 3, 3)))
    flip = bool(rng.integers(0, 2))
    sgn = -1.0 if flip else 1.0
    ys = art.c[1] + sgn * np.linspace(-radius * 0.9, radius * 0.9, H)
    ang = np.linspace(-1, 1, W) * np.radians(35) * 0.45
    dirs = np.stack([sgn * np.sin(ang), np.zeros(W), -np.cos(ang)], 1)
    hx = art.c[0] + rng.uniform(-6, 6)
    src = np.stack([np.full(H, hx), ys, np.full(H, 90.0)], 1)
    orig, D = np.repeat(src, W, 0), np.tile(dirs, (H, 1))
    t = art.intersect(orig, D)
    P = orig + D * t[:, None]
    cosi = np.einsum("ij,ij->i", unit(P - art.c), -D)
    base = 0.03 * (1 - cosi) ** 1.5 + 0.01 * ((P[:, 2] - art.c[2]) / radius)
    line = np.repeat(np.arange(H), W).astype(float)
    inten = np.clip(cosi * rng.uniform(0.3, 1.0) + rng.normal(0, 0.05, len(P)), 0, 1)
    passid = line * n_pass // H
    tt = (line + rng.integers(0, H)) / 200.0  # s since scan start (200 profiles/s)
    u = sgn * (P[:, 0] - hx)  # along the head's laser line (head X)
    extra = np.zeros(len(P))
    for eff, m in (({effect: mag} if effect else {}) | (also or {})).items():
        if eff == "intensity":  # reflectance-dependent range bias
            extra += m * (inten - 0.5) * 2
        elif eff == "pass":  # per-pass offset along the ray
            extra += m * rng.normal(0, 1, n_pass)[passid.astype(int)]
        elif eff == "drift":  # range drift over scan time (a thermal cycle of period 0.15 s)
            extra += m * np.sin(2 * np.pi * tt / 0.15)
        elif eff == "line":  # distortion along the laser line (a ripple of period 2π·6 mm)
            extra += m * np.sin(u / 6.0)
        elif eff == "xscale":  # a ripple of the cell's x axis (e.g. a worn ball screw), period 2π·3 mm in x
            extra += m * np.sin(P[:, 0] / 3.0)
        elif eff == "vibration":  # head vibration locked to the scan start: 6 periods per scan (200 profiles/s)
            extra += m * np.sin(2 * np.pi * tt / VIB_PERIOD_S)
        elif eff == "vibration_free":  # the same vibration with a random phase per scan (not locked to t)
            extra += m * np.sin(2 * np.pi * tt / VIB_PERIOD_S + rng.uniform(0, 2 * np.pi))
    P = P + D * (base + extra + rng.normal(0, noise, len(P)))[:, None]
    fields = {"intensity": inten, "line": line, "t": tt, "u": u, "pass": passid}
    pose = HeadPose(np.array([hx, ys[0], 90.0]), np.diag([sgn, sgn, 1.0]))
    return Scan(P.reshape(H, W, 3), ScanSettings(10, 4, 0.5), pose,
                "xm-ls90", fields={k: v.reshape(H, W).astype(np.float32) for k, v in fields.items()}, artifact=art)


CFG = dict(iterations=120, max_iter=1, trace=TraceConfig(n_perm=49))


@pytest.fixture(scope="module")
def clean_model() -> GivenModel:
    """The model of the current (study) features, trained on scans WITHOUT any undeclared effect."""
    clean = from_scans([sim_scan(1000 + k) for k in range(6)])
    return GivenModel(fit_family("catboost", clean.X, clean.errors, clean.feature_names, seed=0, iterations=150))


def _loop(effect, mag, seed, n=8, given=None, **kw):
    scans = [sim_scan(seed * 100 + k, effect, mag) for k in range(n)]
    data = from_scans(scans)
    return data, run_loop(data, LoopConfig(seed=seed, **{**CFG, **kw}), given=given)


@pytest.mark.parametrize("effect,mag,seed,expected", [
    ("drift", 0.02, 0, "field_t"),
    ("line", 0.02, 0, "field_u"),
    ("intensity", 0.03, 1, "field_intensity"),
    ("xscale", 0.02, 1, "x"),  # no field carries it: only the derived coordinate candidate can
])
def test_loop_names_injected_effect_and_cuts_error(clean_model, effect, mag, seed, expected):
    _, res = _loop(effect, mag, seed, given=clean_model)
    rep = res.report
    assert rep["schema"] == "xmetro.loop.report/2"
    assert rep["selected"] is not None and rep["selected"]["name"] == expected, rep["candidates"][:3]
    assert rep["selected"]["finding"] == "predictive" and rep["predictive"]["added"] == [expected]
    assert rep["candidates"][0]["significant"]
    before = np.mean([rep["before"][a]["mae"] for a in "xyz"])
    after = np.mean([rep["after"][a]["mae"] for a in "xyz"])
    assert after < 0.75 * before, (before, after)
    assert rep["after"]["normal"]["p95"] < rep["before"]["normal"]["p95"]
    assert rep["predictive"]["after"] == rep["after"] and rep["diagnostic"]["findings"] == []


@pytest.mark.parametrize("mag,seed", [(0.02, 0), (0.01, 2)])
def test_per_pass_offset_is_diagnostic_not_live(clean_model, mag, seed):
    """A per-pass offset needs each scan's own ground truth: it is reported as a diagnostic finding (size per pass
    with its bootstrap uncertainty, what would fix it); the live (predictive) figures do not move."""
    _, res = _loop("pass", mag, seed, given=clean_model)
    rep = res.report
    assert rep["selected"] is None and rep["predictive"]["added"] == []
    assert rep["after"] == rep["before"]  # nothing a live node could use
    (f,) = rep["diagnostic"]["findings"]
    assert f["variable"] == "field_pass" and f["kind"] == "offset" and f["needs_ground_truth"]
    assert "pass" in f["structure"] and "register the passes" in f["fix"]
    tab = f["offsets"]
    assert tab["n_identities"] == 8 * 4 and len(tab["per_identity"]) == 32
    assert all(len(r["se_um"]) == 3 and "pass=" in r["identity"] for r in tab["per_identity"])
    # the injected per-pass offsets are N(0, mag) along the ray: their fitted size is of that order
    assert 0.3 * mag * 1e3 < tab["median_um"] < 3 * mag * 1e3, tab["median_um"]
    assert tab["median_se_um"] < 0.5 * tab["median_um"]
    wg = rep["diagnostic"]["eval_with_offsets"]
    before = np.mean([rep["before"][a]["mae"] for a in "xyz"])
    assert np.mean([wg[a]["mae"] for a in "xyz"]) < 0.75 * before


def test_vibration_over_t_is_named_and_mostly_removed(clean_model):
    """A head vibration over the profile time t, 6 periods per scan, amplitude 2× the noise (8 µm), locked to the
    scan start: named ``field_t`` (the spectral test gives its frequency: 30 Hz), added as a feature, and the added
    feature removes at least half of its excess error on the held-out clouds (excess: against the same scans
    without the vibration)."""
    rep = _loop("vibration", 0.008, 0, given=clean_model)[1].report
    clean = _loop(None, 0.0, 0, given=clean_model)[1].report
    assert rep["selected"]["name"] == "field_t", rep["candidates"][:3]
    assert clean["selected"] is None
    sp = next(c for c in rep["candidates"] if c["name"] == "field_t")["spectral"]
    assert sp["significant"] and abs(sp["peak_frequency"] - 1 / VIB_PERIOD_S) < 1.0 and sp["phase_coherence"] > 0.9
    for k in ("mae", "rmse"):
        b, a, c = (r["normal"][k] for r in (rep["before"], rep["after"], clean["before"]))
        assert b > 1.2 * c  # the vibration is there
        assert (b - a) >= 0.5 * (b - c), (k, b, a, c)


def test_vibration_with_free_phase_is_a_diagnostic_oscillation(clean_model):
    """The same vibration with a random phase per scan: t cannot predict it (no live improvement), but the
    phase-free spectral test names it, with its frequency, as a diagnostic oscillation."""
    rep = _loop("vibration_free", 0.008, 0, given=clean_model)[1].report
    assert rep["selected"] is None or rep["selected"]["name"] != "field_t"
    sp = next(c for c in rep["candidates"] if c["name"] == "field_t")["spectral"]
    assert sp["significant"] and abs(sp["peak_frequency"] - 1 / VIB_PERIOD_S) < 1.0 and sp["phase_coherence"] < 0.9
    osc = [f for f in rep["diagnostic"]["findings"] if f["kind"] == "oscillation"]
    assert osc and osc[0]["variable"] == "field_t"


def test_loop_iterates_over_two_effects_then_stops(clean_model):
    """Two undeclared effects at once (a thermal drift over scan time and a reflectance-dependent range bias): the
    loop adds one per iteration, both named in the first two, each lowering the held-out error, and stops by itself
    once nothing significant and useful is left (before its bound of 5 iterations)."""
    scans = [sim_scan(300 + k, "drift", 0.02, also={"intensity": 0.03}) for k in range(8)]
    res = run_loop(from_scans(scans), LoopConfig(seed=3, **{**CFG, "max_iter": 5}), given=clean_model)
    its = res.report["iterations"]
    added = [it["selected"]["name"] for it in its if it["selected"]]
    assert set(added[:2]) == {"field_t", "field_intensity"}, [it["candidates"][:3] for it in its]
    assert its[-1]["selected"] is None and len(its) < 5  # stopped: nothing significant (or useful) left
    maes = [np.mean([it["before"][a]["mae"] for a in "xyz"]) for it in its[:3]]
    assert maes[1] < 0.95 * maes[0] and maes[2] < 0.9 * maes[1], maes
    assert res.added_features[:2] == added[:2]


def test_identity_candidate_is_tried_when_continuous_ones_fail(clean_model):
    """A per-pass offset together with a reflectance bias: both are found — the reflectance bias as a predictive
    feature (live figures improve), the per-pass offset as a diagnostic finding (failing continuous candidates must
    not use up the tries of the identity candidate)."""
    scans = [sim_scan(300 + k, "intensity", 0.03, also={"pass": 0.02}) for k in range(8)]
    res = run_loop(from_scans(scans), LoopConfig(seed=3, **{**CFG, "max_iter": 4}), given=clean_model)
    sel = {it["selected"]["name"]: it["selected"] for it in res.report["iterations"] if it["selected"]}
    assert sel["field_pass"]["correction"] == "offset" and sel["field_pass"]["finding"] == "diagnostic"
    assert "field_intensity" in res.added_features and res.report["selected"]["name"] == "field_intensity"
    assert [f["variable"] for f in res.report["diagnostic"]["findings"]] == ["field_pass"]
    before = np.mean([res.report["before"][a]["mae"] for a in "xyz"])
    # live: the intensity feature only. Its live effect is not asserted: the per-pass offsets (±20 µm) dominate what
    # a live node is left with, and the corrector learnt on 3 training scans carrying them does not reliably help
    # the eval scans here (docs/closed-loop.md, limits); the report keeps the live figures apart.
    assert res.report["predictive"]["after"] == res.report["after"]
    assert res.report["predictive"]["steps"][0]["variable"] == "field_intensity"
    wg = res.report["diagnostic"]["eval_with_offsets"]  # with the per-pass offsets (needs the ground truth)
    assert np.mean([wg[a]["mae"] for a in "xyz"]) < 0.5 * before


def test_loop_reports_none_without_effect(clean_model, tmp_path):
    from xmetro_ros.loop.report import write_report

    _, res = _loop(None, 0.0, 3, given=clean_model)
    assert res.report["selected"] is None
    assert res.report["iterations"][0]["selected"] is None
    assert res.report["diagnostic"]["findings"] == [] and res.report["predictive"]["added"] == []
    # the new scorers ran (multi-resolution bins, spectral test over t and positions) and stayed silent
    spec = [c for c in res.report["candidates"] if c["spectral"]]
    assert {"field_t", "field_u", "scan_position"} <= {c["name"] for c in spec}
    assert not any(c["significant"] or c["spectral"]["significant"] for c in spec)
    path = write_report(res, tmp_path)
    import json

    rep = json.loads(path.read_text())
    for key in ("candidates", "selected", "before", "after", "iterations"):
        assert key in rep
    assert set(rep["before"]) >= {"x", "y", "z"} and set(rep["before"]["x"]) >= {"mae", "r2", "p95"}
    assert all({"name", "score", "p_value"} <= set(c) for c in rep["candidates"])
    assert (tmp_path / "report.md").exists()


def test_exported_model_lists_field_feature(clean_model, tmp_path):
    from xmetro_ros.judge.inference import ModelSet
    from xmetro_ros.loop.export import export_loop_model

    data, res = _loop("intensity", 0.03, 1, max_iter=1, given=clean_model)
    assert res.added_features == ["field_intensity"]
    out = export_loop_model(res, data, tmp_path / "model")
    ms = ModelSet.load(out)
    assert ms.feature_names[-1] == "field_intensity" and "field_intensity" in ms.card["feature_names"]
    assert "intensity" in ms.required_fields()
    pred = ms.predict(res.X[:50].astype(np.float32))
    assert pred.shape == (50, 3) and np.all(np.isfinite(pred))
    # the exported model, given back to the loop: intensity is now a model feature (a control, never selected)
    data2 = from_scans([sim_scan(700 + k, "intensity", 0.03) for k in range(6)], feature_names=ms.feature_names)
    res2 = run_loop(data2, LoopConfig(**CFG), given=GivenModel(ms))
    cand = {c["name"]: c for c in res2.report["candidates"]}
    assert cand["field_intensity"]["in_model"]
    assert res2.report["selected"] is None or res2.report["selected"]["name"] != "field_intensity"


def test_holm_and_noise_candidate_not_significant():
    assert np.allclose(holm(np.array([0.01, 0.04, 0.03])), [0.03, 0.06, 0.06])


_CONCAT_ORDER = """
import numpy as np
from xmetro_ros.loop.data import LoopData
def part(names, geo):
    n = 2
    return LoopData(points=np.zeros((n, 3)), normals=np.zeros((n, 3)), errors=np.zeros((n, 3)),
                    X=np.zeros((n, 1), np.float32), feature_names=["f"], fields={k: np.zeros(n) for k in names},
                    group=np.zeros(n, np.int64), order=np.arange(n), geometry={k: np.zeros(n) for k in geo})
names = [f"field_{w}" for w in "t u line intensity time s pass reflectance".split()]
d = LoopData.concat([part(names, ["u", "s", "L"]), part(names[::-1] + ["field_x"], ["L", "s", "u"])])
print(",".join(d.fields), ",".join(d.geometry))
"""


def test_concat_keeps_the_first_parts_field_order_whatever_the_hash_seed():
    """The trace seeds each candidate by its position, so the fields' order must not depend on the process's
    hash seed (tables built on Dask workers have others); a set of names did (test_loop_dask failed 1 run in 4)."""
    import os
    import subprocess
    import sys

    outs = {subprocess.run([sys.executable, "-c", _CONCAT_ORDER], capture_output=True, text=True, check=True,
                           env={**os.environ, "PYTHONHASHSEED": str(seed)}).stdout.strip() for seed in range(6)}
    fields = ",".join(f"field_{w}" for w in "t u line intensity time s pass reflectance".split())
    assert outs == {f"{fields} u,s,L"}


def test_bad_inputs(tmp_path):
    need_shared(DATA)
    with pytest.raises(LoopInputError, match="does not exist"):
        load_inputs([tmp_path / "missing.mcap"], "sphere:radius=40")
    with pytest.raises(ArtifactSpecError):
        load_inputs([DATA / "measured" / "nist_tls_spheres_r50"], "sphere:diameter=40")
    bad = tmp_path / "bad.xyz"
    bad.write_text("not numbers\n")
    with pytest.raises((LoopInputError, ValueError)):
        load_inputs([bad], "sphere:radius=50,center=fit")
    # radius far from the data → clear error, not a silently bad fit
    with pytest.raises(ValueError, match="does not fit"):
        from_scans([sim_scan(0)], Sphere(2.0), fit_center=True)
    # too few clouds to hold out
    data = from_scans([sim_scan(k) for k in range(2)])
    with pytest.raises(LoopInputError, match="too few"):
        run_loop(data, LoopConfig(**CFG))
    # a field named as a candidate but absent
    with pytest.raises(LoopInputError, match="field_reflectance"):
        build_candidates(data, include=["field_reflectance"])


def test_bag_input_keeps_fields_and_clouds(tmp_path):
    from xmetro_ros.ros.scan_io import write_scans

    scans = [sim_scan(k, "pass", 0.02) for k in range(4)]
    bag = write_scans(tmp_path / "scans.mcap", scans)
    data = load_inputs([bag], None, read_bag=read_scans)
    assert len(data.groups) == 4 and {"intensity", "t", "u", "pass", "line"} <= set(data.fields)
    direct = from_scans(scans)
    assert data.n == direct.n
    assert np.allclose(data.errors, direct.errors, atol=1e-4)


def _cli(argv: list[str]) -> int:
    import argparse

    from xmetro_ros.apps import loop as cli

    parser = argparse.ArgumentParser()
    cli.register(parser.add_subparsers())
    args = parser.parse_args(["loop", *argv])
    return args.func(args)


def test_cli_end_to_end_and_errors(tmp_path, capsys):
    import json

    from xmetro_ros.ros.scan_io import write_scans

    bag = write_scans(tmp_path / "pass.mcap", [sim_scan(500 + k, "pass", 0.03) for k in range(6)])
    out = tmp_path / "out"
    rc = _cli([str(bag), "--out", str(out), "--n-perm", "29", "--iterations", "60", "--max-iter", "1"])
    assert rc == 0, capsys.readouterr().err
    rep = json.loads((out / "report.json").read_text())
    assert rep["selected"] is None and rep["diagnostic"]["findings"][0]["variable"] == "field_pass"
    md = (out / "report.md").read_text()
    assert "## Predictive" in md and "## Diagnostic" in md and "field_pass" in md.split("## Diagnostic")[1]
    assert md.count("![") == len(rep["plots"]) == 1
    assert _cli([str(bag), "--out", str(out), "--artifact", "cube:side=3"]) == 2
    assert "unknown artifact kind" in capsys.readouterr().err
    assert _cli([str(bag), "--out", str(out), "--candidates", "field_nope"]) == 2
    assert "field_nope" in capsys.readouterr().err


def test_spectral_test_finds_frequency_and_phase_coherence():
    """The spectral test alone on synthetic residuals (6 clouds of 800 points, noise σ = 1): a sinusoid of amplitude
    1 at 5 cycles per unit is found at its frequency with coherence ≈ 1 when its phase is locked to x, ≈ low when
    the phase is random per cloud; pure noise stays at the null (score ≈ 0, p not small)."""
    from xmetro_ros.loop.trace import TraceConfig, cv_folds, spectral_test

    rng = np.random.default_rng(0)
    n, G = 800, 6
    x = np.concatenate([np.sort(rng.uniform(0, 1.2, n)) + rng.uniform(0, 0.5) for _ in range(G)])
    g = np.repeat(np.arange(G), n)
    noise = rng.normal(0, 1, (n * G, 3))
    cfg = TraceConfig(n_perm=49)
    folds = cv_folds(g, np.arange(n * G), cfg.n_folds, by="group", block_size=24, seed=0)
    phases = {"locked": np.zeros(G), "free": rng.uniform(0, 2 * np.pi, G)}
    for kind, ph in phases.items():
        R = noise.copy()
        R[:, 2] += np.sin(2 * np.pi * 5.0 * x + ph[g])
        out = spectral_test(R, x, g, folds, cfg, np.random.default_rng(1))
        assert out is not None and abs(out["peak_frequency"] - 5.0) < 0.3, out
        assert out["score"] > 0.1 and out["p_value"] < 0.02 and abs(out["amplitude_mm"] - 1.0) < 0.3
        assert (out["phase_coherence"] > 0.95) if kind == "locked" else (out["phase_coherence"] < 0.8), out
    out = spectral_test(noise, x, g, folds, cfg, np.random.default_rng(1))
    assert abs(out["score"]) < 0.01 and out["p_value"] > 0.05, out
