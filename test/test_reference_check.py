"""Reference-scan monitoring (xmetro_ros.monitor.reference_check, ROS-free): simulated scans of a certified Ø25 sphere
at a
known position, judged by the shipped model (the node's own processing path, ScanHandler), checked against the
sphere. Truth from the simulator: a stable scanner, and one whose laser line tilts by 2 mrad (a range error of
2 µm per mm along the line, ±25 µm at the sphere's edges, the size of the noise) from a given reference scan on.

Streams are resampled from pools of simulated per-scan statistics (as test_drift.py does), so the false-alarm rate
and the detection delay are measured over many streams: asserted ≤ 3 % false alarms over 200 stable streams of 24
reference scans, and WARN within 3 reference scans of the switch (docs/closed-loop.md quotes the figures)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from xmetro_ros.judge.inference import ModelSet
from xmetro_ros.judge.scan_handler import HandlerParams, ScanHandler
from xmetro_ros.monitor.drift import DriftConfig, DriftMonitor
from xmetro_ros.monitor.reference_check import ReferenceChecker, ReferenceSpec, live_candidates, screen_candidates
from xmetro_ros.scan.artifacts import Sphere
from xmetro_ros.scan.scanner import ScannerModel, ScanSettings
from xmetro_ros.sim import simulate_scan

RADIUS = 12.5
CENTER = (1.0, -2.0, 0.5)
SETTINGS = ScanSettings(6.0, 3.0, 0.5)
TILT = 0.002  # mm of range error per mm along the laser line
STREAM, SWITCH, MAX_DELAY = 24, 12, 3


def reference_scan(seed: int, tilt: float = 0.0, radius: float = RADIUS):
    """A simulated scan of the reference sphere; ``tilt``: the laser line's range error per mm of line position
    (measured points pushed along the looking-down laser direction, −Z)."""
    scan = simulate_scan(Sphere(radius, CENTER), SETTINGS, seed=seed)
    if tilt:
        pts = scan.points.copy()
        pts[..., 2] -= tilt * scan.fields["u"]
        scan = replace(scan, points=pts)
    return scan


@pytest.fixture(scope="module")
def handler() -> ScanHandler:
    return ScanHandler(ModelSet.load(None), ScannerModel.load(), HandlerParams())


@pytest.fixture(scope="module")
def pools(handler) -> dict:
    """Per-scan statistics of stable and tilted reference scans (a checker that never leaves its warm-up)."""
    spec = ReferenceSpec(RADIUS, CENTER)

    def stats(seeds: range, tilt: float) -> list[dict]:
        chk = ReferenceChecker(spec, DriftConfig(warmup=10_000))
        out = []
        for s in seeds:
            r = handler.process(reference_scan(s, tilt))
            res = chk.check(r.prepared.points, r.predictions, r.row_uncertainty)
            assert res.state == "WARMUP" and res.drift is not None
            out.append(res.drift.stats)
        return out

    return {"stable": stats(range(100, 124), 0.0), "tilt": stats(range(200, 208), TILT)}


def test_stable_reference_scans_agree_with_the_model(pools):
    # the model's prediction and interval hold on the stable scanner: residual mean ~0, coverage near 95 %
    mean = np.array([s["residual_mean"] for s in pools["stable"]])
    cov = np.array([s["coverage"] for s in pools["stable"]])
    assert np.all(np.abs(mean) < 0.002), mean
    assert np.all((cov > 0.92) & (cov < 0.99)), cov


def test_false_alarms_and_detection_delay_over_resampled_streams(pools):
    false_alarms, delays = 0, []
    n = 200
    for k in range(n):
        rng = np.random.default_rng(k)
        stable = [pools["stable"][i] for i in rng.integers(0, len(pools["stable"]), STREAM)]
        mon = DriftMonitor()
        states = [mon.update_stats(s) for s in stable]
        false_alarms += any(st.state == "WARN" for st in states)
        stream = ([pools["stable"][i] for i in rng.integers(0, len(pools["stable"]), SWITCH)]
                  + [pools["tilt"][i] for i in rng.integers(0, len(pools["tilt"]), STREAM - SWITCH)])
        mon = DriftMonitor()
        first = next((st.n_scans for st in (mon.update_stats(s) for s in stream) if st.state == "WARN"), None)
        assert first is not None, "tilt not detected"
        delays.append(first - SWITCH)
    d = np.array(delays)
    assert false_alarms / n <= 0.03, false_alarms
    assert d.min() >= 1 and d.max() <= MAX_DELAY, d


def test_checker_states_candidate_and_mismatch(handler):
    chk = ReferenceChecker(ReferenceSpec(RADIUS, CENTER), DriftConfig(warmup=5))
    seen = []
    for k in range(8):
        r = handler.process(reference_scan(300 + k, TILT if k >= 5 else 0.0))
        res = chk.check(r.prepared.points, r.predictions, r.row_uncertainty, live_candidates(r.prepared))
        seen.append(res)
    assert [s.state for s in seen[:5]] == ["WARMUP"] * 4 + ["OK"]
    warn = [s for s in seen if s.state == "WARN"]
    assert warn and warn[0].drift is not None and warn[0].drift.first_warn_scan == 6
    # looking down, the line position u and the scan-frame x coincide: the screening names one of them
    assert warn[0].candidate in ("u", "x"), warn[0].screening
    assert abs(warn[0].candidate_rho) >= 0.3 and warn[0].candidate_p < 1e-6
    assert "candidate effect" in warn[0].message
    # a scan of another sphere (or the right one where it is not): MISMATCH, not fed to the monitor
    r = handler.process(simulate_scan(Sphere(20.0, CENTER), SETTINGS, seed=9))
    res = chk.check(r.prepared.points, r.predictions, r.row_uncertainty)
    assert res.state == "MISMATCH" and chk.monitor.n == 8 and "does not show the sphere" in res.message
    # a fitted centre absorbs a shift of the whole sphere (the documented consequence: a pose drift is invisible):
    # the same scan moved by 30 µm gives the same residual, where the known centre sees the shift
    r = handler.process(reference_scan(301))
    moved = r.prepared.points + np.array([0.0, 0.0, 0.03])
    fit = [ReferenceChecker(ReferenceSpec(RADIUS, (0.0, 0.0, 0.0), fit_center=True)) for _ in range(2)]
    known = [ReferenceChecker(ReferenceSpec(RADIUS, CENTER)) for _ in range(2)]
    a, b = (c.check(p, r.predictions, r.row_uncertainty) for c, p in zip(fit, (r.prepared.points, moved), strict=True))
    assert a.state == b.state == "WARMUP" and abs(a.residual_mean_mm - b.residual_mean_mm) < 1e-4
    a, b = (c.check(p, r.predictions, r.row_uncertainty) for c, p in zip(known, (r.prepared.points, moved),
                                                                          strict=True))
    assert abs(a.residual_mean_mm - b.residual_mean_mm) > 0.01
    chk.reset()
    assert chk.monitor.n == 0


def test_spurious_returns_are_left_out():
    rng = np.random.default_rng(0)
    sphere = Sphere(RADIUS, CENTER)
    n = rng.normal(size=(4000, 3))
    n[:, 2] = np.abs(n[:, 2]) + 0.3
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    pts = sphere.c + n * (RADIUS + rng.normal(0, 0.005, (4000, 1)))
    pts[:20] += n[:20] * 0.8  # 20 spurious returns 0.8 mm off the surface
    res = ReferenceChecker(ReferenceSpec(RADIUS, CENTER)).check(pts, np.zeros_like(pts), np.full_like(pts, 0.01))
    assert res.trimmed >= 20 and res.residual_rms_mm < 0.008


def test_screening_names_the_variable_and_corrects_for_multiplicity():
    rng = np.random.default_rng(1)
    x = rng.uniform(-10, 10, 5000)
    r = 0.002 * x + rng.normal(0, 0.01, 5000)
    out = screen_candidates(r, {"x": x, "noise": rng.normal(size=5000), "const": np.ones(5000)})
    assert set(out) == {"x", "noise"}  # a constant candidate is left out
    assert out["x"]["p"] < 1e-10 and out["noise"]["p"] > 0.01
    with pytest.raises(ValueError, match="radius"):
        ReferenceSpec(0.0)
